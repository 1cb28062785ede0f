"""The PettingZoo environment (env stage): API, observations, rewards, success rules, episodes."""

import dataclasses
import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

from kgnavbench.env import (
    ARRIVAL_REWARD,
    STEP_REWARD,
    SUCCESS_REWARD,
    EnvError,
    NavigationEnv,
    UnknownOptionWarning,
    parallel_env,
)
from kgnavbench.graph import OPEN, STOP
from kgnavbench.kitchens import object_types
from kgnavbench.tasks import MIN_START_DISTANCE, START_PITCH
from kgnavbench.world import ACTIONS, Pose

EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"
APPLE = "Apple|-00.47|+01.15|+00.48"
MOVE_AHEAD, MOVE_BACK, MOVE_RIGHT, MOVE_LEFT = range(4)
ROTATE_RIGHT, ROTATE_LEFT, LOOK_UP, LOOK_DOWN = range(4, 8)
A0 = "navigator_0"


@pytest.fixture(scope="module")
def tasks(floorplan1_tasks):
    return floorplan1_tasks


@pytest.fixture(scope="module")
def graph(tasks):
    return tasks.graph


@pytest.fixture
def make_env(tasks):
    def make(**kwargs):
        kwargs.setdefault("n_agents", 1)
        kwargs.setdefault("privileged", True)  # these tests walk by the expert action and check states
        kwargs.setdefault("tasks", tasks)
        return parallel_env(kitchen="FloorPlan1", **kwargs)

    return make


@pytest.fixture(scope="module")
def egg_start(graph):
    """Closed state facing the closed fridge: OpenObject opens it and shows the egg."""
    return graph.state_of(Pose((-4, 4), 270, 30))


def episode(target, start, max_steps=100):
    return {"target": target, "start": int(start), "max_steps": max_steps}


def run(env, actions, agent=A0):
    """Step one agent through actions; the per-step rewards, terminations, truncations and infos."""
    out = []
    for a in actions:
        _, rewards, terms, truncs, infos = env.step({agent: a})
        out.append((rewards[agent], terms[agent], truncs[agent], infos[agent]))
    return out


# ------------------------------------------------------------------------------------------------
# PettingZoo's own checks


def test_constructor_and_spaces(make_env, tasks):
    env = make_env(n_agents=3)
    assert isinstance(env, NavigationEnv)
    assert env.possible_agents == ["navigator_0", "navigator_1", "navigator_2"]
    assert env.agents == []
    for agent in env.possible_agents:
        assert env.action_space(agent).n == len(ACTIONS) == 10
        assert env.action_space(agent) is env.action_space(agent)
        assert env.observation_space(agent) is env.observation_space(agent)
    assert env.metadata["name"] == "kgnavbench_v0"


def test_pettingzoo_parallel_api(make_env):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # PettingZoo reports API slips as warnings
        # (but its test resets with options={"options": 1}, which kgnavbench names in a warning)
        warnings.simplefilter("ignore", UnknownOptionWarning)
        parallel_api_test(make_env(n_agents=3, max_steps=60), num_cycles=200)


def test_pettingzoo_parallel_api_with_truncation(make_env):
    # stop_ends=False: random Stops rarely end an episode, so agents live until max_steps
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.simplefilter("ignore", UnknownOptionWarning)
        parallel_api_test(make_env(n_agents=2, stop_ends=False, max_steps=150), num_cycles=200)


def test_pettingzoo_parallel_seed(make_env):
    parallel_seed_test(lambda: make_env(n_agents=3, max_steps=80), num_cycles=200)


# ------------------------------------------------------------------------------------------------
# Observations


def test_observations_match_the_state_graph(make_env, tasks, graph):
    env = make_env(n_agents=3)
    observations, infos = env.reset(seed=3)
    assert set(observations) == set(infos) == set(env.agents) == set(env.possible_agents)
    n_types = len(object_types())
    assert n_types == 125
    for agent, obs in observations.items():
        assert set(obs) == {"view", "target", "view_objects", "target_objects"}
        assert obs["view"].shape == obs["target"].shape == (84, 84, 3)
        assert obs["view_objects"].shape == obs["target_objects"].shape == (n_types,)
        assert all(v.dtype == np.uint8 for v in obs.values())
        assert env.observation_space(agent).contains(obs)
        info = infos[agent]
        target = tasks.target(info["target"])
        state = info["state"]
        np.testing.assert_array_equal(obs["target"], graph.views[target.destination])
        np.testing.assert_array_equal(obs["view"], graph.views[state])
        np.testing.assert_array_equal(obs["target_objects"], graph.object_vectors[target.destination])
        np.testing.assert_array_equal(obs["view_objects"], graph.object_vectors[state])
        # the target's own type is among the objects its image shows
        assert obs["target_objects"][object_types().index(target.type)] == 1
    for a in range(len(ACTIONS) - 1):  # everything but Stop, so nobody leaves
        observations, _, _, _, infos = env.step(dict.fromkeys(env.agents, a))
        for agent, obs in observations.items():
            assert env.observation_space(agent).contains(obs)
            np.testing.assert_array_equal(obs["view"], graph.views[infos[agent]["state"]])


def test_reset_infos(make_env, tasks, graph):
    env = make_env(n_agents=4, targets="all")
    _, infos = env.reset(seed=11)
    for info in infos.values():
        target = tasks.target(info["target"])
        start = info["state"]
        assert info["success"] is False
        assert info["path_length"] == info["episode_length"] == info["collisions"] == 0
        assert info["target_kind"] == target.kind
        assert info["target_seen"] == target.seen
        assert info["shortest_path"] == tasks.distances(target)[start]
        assert info["last_view_shows_target"] == (start in target.goal_states)
        # training starts follow the fixed episodes' rules
        assert graph.opened[start] == -1 and graph.pitch[start] == START_PITCH
        assert tasks.distances(target, "destination")[start] >= MIN_START_DISTANCE


def test_observations_are_read_only_views_of_the_cache(make_env):
    # env.py's docstring: "Arrays are read-only views of that cache": writing into an observation
    # raises instead of changing what every later observation shows
    env = make_env()
    observations, _ = env.reset(seed=0)
    writable = [key for key, array in observations[A0].items() if array.flags.writeable]
    assert writable == []
    with pytest.raises(ValueError, match="read-only"):
        observations[A0]["view_objects"][:] = 0


def test_a_fresh_graph_is_read_only_too(floorplan1_tasks):
    from kgnavbench.graph import StateGraph

    g = floorplan1_tasks.graph
    fresh = StateGraph(
        g.kitchen, g.world, g.cells, g.cell, g.heading, g.pitch, g.opened, g.next_state, g.ok, g.visible,
        np.array(g.views),
    )  # fmt: skip
    assert not fresh.views.flags.writeable and not fresh.object_vectors.flags.writeable


@pytest.mark.parametrize("bad", [3.7, True, "2", None])
def test_non_integer_starts_and_actions_are_refused(make_env, floorplan1_tasks, bad):
    target = floorplan1_tasks.targets[0]
    env = make_env()
    with pytest.raises(EnvError, match="integers"):
        env.reset(options={"episodes": [{"target": target.object_id, "start": bad}]})
    env.reset(seed=0)
    with pytest.raises(EnvError, match="integers"):
        env.step({agent: bad for agent in env.agents})


def test_an_unknown_success_rule_for_distances_is_refused(floorplan1_tasks):
    from kgnavbench.graph import TaskError

    with pytest.raises(TaskError, match="visble"):
        floorplan1_tasks.distances(floorplan1_tasks.targets[0], "visble")


# ------------------------------------------------------------------------------------------------
# Rewards and success


def oracle_episode(env, target, start):
    """Follow expert_action to the end; (rewards, last infos)."""
    rewards, last = [], None
    _, infos = env.reset(options={"episodes": [episode(target, start, max_steps=500)]})
    info = infos[A0]
    while env.agents:
        _, r, terms, truncs, infos = env.step({A0: info["expert_action"]})
        rewards.append(r[A0])
        info = last = infos[A0]
        assert not truncs[A0]
    assert terms[A0]
    return rewards, last


@pytest.mark.parametrize("object_id", [EGG, APPLE, FRIDGE])
@pytest.mark.parametrize("rule", ["visible", "destination"])
def test_the_oracle_succeeds_on_the_fixed_episodes(make_env, tasks, object_id, rule):
    env = make_env(success_rule=rule)
    target = tasks.target(object_id)
    dist = tasks.distances(target, rule)
    for start in target.starts[:5]:
        rewards, info = oracle_episode(env, object_id, start)
        shortest = int(dist[start])
        assert info["success"] is True
        assert info["shortest_path"] == shortest
        assert info["path_length"] == shortest
        assert info["episode_length"] == shortest + 1
        assert len(rewards) == shortest + 1
        assert info["collisions"] == 0
        assert info["last_view_shows_target"] is True
        assert info["state"] in (target.goal_states if rule == "visible" else (target.destination,))
        # -0.01 a step, +0.01 on the step that first reaches a goal state, +10 for the Stop after it
        expected = [STEP_REWARD] * (shortest + 1)
        if shortest > 0:
            expected[shortest - 1] += ARRIVAL_REWARD
        expected[-1] += SUCCESS_REWARD
        assert rewards == pytest.approx(expected)
        assert rewards[-1] == pytest.approx(-0.01 + 10)


def test_agents_run_their_episodes_independently(make_env, tasks):
    env = make_env(n_agents=3)
    targets = [EGG, APPLE, FRIDGE]
    episodes = [episode(t, tasks.target(t).starts[0], max_steps=500) for t in targets]
    _, infos = env.reset(options={"episodes": episodes})
    lengths = {a: infos[a]["shortest_path"] + 1 for a in env.agents}
    assert len(set(lengths.values())) > 1  # they finish at different times
    finished, t = {}, 0
    while env.agents:
        t += 1
        before = list(env.agents)
        obs, rewards, terms, truncs, infos = env.step({a: infos[a]["expert_action"] for a in env.agents})
        assert set(obs) == set(rewards) == set(terms) == set(truncs) == set(infos) == set(before)
        for a in before:
            if terms[a]:
                finished[a] = (t, infos[a]["success"], infos[a]["target"])
        assert set(env.agents) == {a for a in before if not terms[a] and not truncs[a]}
    assert finished == {a: (lengths[a], True, targets[i]) for i, a in enumerate(env.possible_agents)}
    # once every agent is done, a step with no actions returns nothing
    assert env.step({}) == ({}, {}, {}, {}, {})


def test_fewer_episodes_than_agents_leaves_the_rest_out(make_env, tasks):
    env = make_env(n_agents=3)
    observations, infos = env.reset(options={"episodes": [episode(APPLE, tasks.target(APPLE).starts[0])]})
    assert env.agents == [A0]
    assert set(observations) == set(infos) == {A0}
    observations, *_ = env.step({A0: ROTATE_RIGHT})
    assert set(observations) == {A0}


def test_egg_needs_the_fridge_open(make_env, graph, egg_start):
    env = make_env(success_rule="visible")  # the egg in view from the open fridge, anywhere
    # Stop in front of the closed fridge: the egg is not visible, the episode ends in failure
    _, infos = env.reset(options={"episodes": [episode(EGG, egg_start)]})
    assert infos[A0]["shortest_path"] == 1
    assert infos[A0]["expert_action"] == OPEN
    assert infos[A0]["last_view_shows_target"] is False
    [(reward, term, trunc, info)] = run(env, [STOP])
    assert (reward, term, trunc) == (pytest.approx(STEP_REWARD), True, False)
    assert info["success"] is False
    assert info["path_length"] == 0 and info["episode_length"] == 1
    assert env.agents == []

    # OpenObject shows the egg (first arrival), then Stop succeeds
    env.reset(options={"episodes": [episode(EGG, egg_start)]})
    (r1, term1, _, info1), (r2, term2, _, info2) = run(env, [OPEN, STOP])
    assert r1 == pytest.approx(STEP_REWARD + ARRIVAL_REWARD) == pytest.approx(0.0)
    assert not term1 and info1["last_view_shows_target"] and info1["expert_action"] == STOP
    assert info1["state"] == graph.next_state[egg_start, OPEN]
    assert graph.opened[info1["state"]] == graph.world.index(FRIDGE)
    assert r2 == pytest.approx(STEP_REWARD + SUCCESS_REWARD)
    assert term2 and info2["success"] is True
    assert info2["path_length"] == 1 and info2["episode_length"] == 2
    assert info2["state"] == info1["state"]  # Stop keeps the fridge open


def test_the_arrival_reward_is_paid_once(make_env, egg_start):
    env = make_env(success_rule="visible")  # the egg in view from the open fridge, anywhere
    env.reset(options={"episodes": [episode(EGG, egg_start)]})
    # open (arrive), look away (the fridge closes), look back, open again (no second bonus), Stop
    steps = run(env, [OPEN, ROTATE_RIGHT, ROTATE_LEFT, OPEN, STOP])
    rewards = [s[0] for s in steps]
    assert rewards == pytest.approx(
        [STEP_REWARD + ARRIVAL_REWARD, STEP_REWARD, STEP_REWARD, STEP_REWARD, STEP_REWARD + SUCCESS_REWARD]
    )
    assert [s[3]["last_view_shows_target"] for s in steps] == [True, False, False, True, True]
    assert steps[-1][3]["success"] and steps[-1][3]["path_length"] == 4


def test_no_arrival_reward_when_starting_on_a_goal(make_env, tasks, graph, egg_start):
    env = make_env(success_rule="visible")  # the egg in view from the open fridge, anywhere
    open_state = int(graph.next_state[egg_start, OPEN])
    _, infos = env.reset(options={"episodes": [episode(EGG, open_state)]})
    assert infos[A0]["shortest_path"] == 0 and infos[A0]["expert_action"] == STOP
    [(reward, term, _, info)] = run(env, [STOP])
    assert reward == pytest.approx(STEP_REWARD + SUCCESS_REWARD)
    assert term and info["success"] and info["path_length"] == 0


def test_a_wrong_stop_is_a_no_op_without_stop_ends(make_env, graph, egg_start):
    env = make_env(stop_ends=False, success_rule="visible")
    env.reset(options={"episodes": [episode(EGG, egg_start)]})
    for k in range(1, 4):
        [(reward, term, trunc, info)] = run(env, [STOP])
        assert reward == pytest.approx(STEP_REWARD)
        assert (term, trunc, info["success"]) == (False, False, False)
        assert info["state"] == egg_start
        assert info["path_length"] == 0 and info["episode_length"] == k
        assert env.agents == [A0]
    (r1, _, _, _), (r2, term, _, info) = run(env, [OPEN, STOP])
    assert r1 == pytest.approx(STEP_REWARD + ARRIVAL_REWARD)
    assert r2 == pytest.approx(STEP_REWARD + SUCCESS_REWARD)
    assert term and info["success"] and info["path_length"] == 1 and info["episode_length"] == 5
    assert env.agents == []


def test_destination_rule_needs_the_destination(make_env, tasks, graph, egg_start):
    egg = tasks.target(EGG)
    open_state = int(graph.next_state[egg_start, OPEN])
    assert open_state in egg.goal_states and open_state != egg.destination  # shows the egg, elsewhere

    env = make_env(success_rule="destination")
    _, infos = env.reset(options={"episodes": [episode(EGG, egg_start)]})
    assert infos[A0]["shortest_path"] == tasks.distances(egg, "destination")[egg_start] > 1
    (r1, _, _, info1), (r2, term, _, info2) = run(env, [OPEN, STOP])
    assert r1 == pytest.approx(STEP_REWARD)  # a goal state under "visible", not under "destination"
    assert info1["last_view_shows_target"] is True
    assert r2 == pytest.approx(STEP_REWARD)
    assert term and info2["success"] is False

    # at the destination itself it succeeds
    _, infos = env.reset(options={"episodes": [episode(EGG, egg.destination)]})
    assert infos[A0]["shortest_path"] == 0
    [(reward, term, _, info)] = run(env, [STOP])
    assert reward == pytest.approx(STEP_REWARD + SUCCESS_REWARD)
    assert term and info["success"] is True

    # the same Stop in front of the open fridge succeeds under "visible"
    env = make_env(success_rule="visible")
    env.reset(options={"episodes": [episode(EGG, egg_start)]})
    assert run(env, [OPEN, STOP])[-1][3]["success"] is True


def test_the_arrival_rule_ends_the_episode_on_arriving_and_stop_is_a_no_op(make_env, tasks, egg_start):
    """Zhu et al.'s rule: arriving at the destination, by any action, is success and ends the episode
    (no Stop); a Stop anywhere is a no-op; Stop ending episodes contradicts the rule and is refused."""
    with pytest.raises(EnvError, match="arrival"):
        make_env(success_rule="arrival")
    env = make_env(success_rule="arrival", stop_ends=False)
    apple = tasks.target(APPLE)
    dist = tasks.distances(apple, "arrival")
    assert (dist == tasks.distances(apple, "destination")).all()  # the same goal: the destination
    for start in apple.starts[:3]:
        shortest = int(dist[start])
        _, infos = env.reset(options={"episodes": [episode(APPLE, start)]})
        [(reward, term, trunc, info)] = run(env, [STOP])  # a Stop: nothing happens
        assert (reward, term, trunc, info["success"]) == (pytest.approx(STEP_REWARD), False, False, False)
        assert info["state"] == start and info["path_length"] == 0
        info, rewards, terms = infos[A0], [], []
        while env.agents:
            assert info["expert_action"] != STOP  # the episode ends before a Stop is ever due
            _, r, term, _, infos = env.step({A0: info["expert_action"]})
            info = infos[A0]
            rewards.append(r[A0])
            terms.append(term[A0])
        assert info["success"] is True and info["state"] == apple.destination
        assert info["path_length"] == shortest and info["episode_length"] == shortest + 1
        assert terms == [False] * (shortest - 1) + [True]
        assert rewards[-1] == pytest.approx(STEP_REWARD + ARRIVAL_REWARD + SUCCESS_REWARD)
    # the visible states that are not the destination are no success under it
    egg = tasks.target(EGG)
    env.reset(options={"episodes": [episode(EGG, egg_start)]})
    [(_, term, _, info)] = run(env, [OPEN])
    assert info["last_view_shows_target"] and info["state"] != egg.destination
    assert (term, info["success"]) == (False, False)


def test_success_is_decided_in_one_place_for_every_rule():
    """tasks.outcome: (success, terminated) from (Stop?, on a goal state?) under each rule."""
    from kgnavbench.tasks import TaskError, outcome

    stop, goal = np.array([True, True, False, False]), np.array([True, False, True, False])
    for rule in ("destination", "visible"):
        success, ends = outcome(rule, stop, goal, True)
        assert success.tolist() == [True, False, False, False] and ends.tolist() == [True, True, False, False]
        success, ends = outcome(rule, stop, goal, False)
        assert success.tolist() == [True, False, False, False] and ends.tolist() == [
            True,
            False,
            False,
            False,
        ]
    success, ends = outcome("arrival", stop, goal, False)
    assert success.tolist() == [True, False, True, False] and ends.tolist() == success.tolist()
    with pytest.raises(TaskError, match="stop_ends must be False"):
        outcome("arrival", stop, goal, True)
    with pytest.raises(TaskError, match="unknown success rule"):
        outcome("nearby", stop, goal, True)


def test_the_envs_step_and_the_rescoring_ask_the_one_success_function(make_env, monkeypatch):
    """The env's step and the visible rule's re-scoring of saved episodes both decide success through
    tasks.outcome (the same function object, called by each)."""
    from kgnavbench import env as env_stage
    from kgnavbench import evaluate, tasks
    from kgnavbench.metrics import EpisodeResult

    assert env_stage.outcome is tasks.outcome is evaluate.outcome
    calls = []

    def spy(rule, stop, on_goal, stop_ends):
        calls.append(rule)
        return tasks.outcome(rule, stop, on_goal, stop_ends)

    monkeypatch.setattr(env_stage, "outcome", spy)
    monkeypatch.setattr(evaluate, "outcome", spy)
    env = make_env()
    env.reset(options={"episodes": [episode(APPLE, 0)]})
    run(env, [9])
    assert calls == ["destination"]
    fields = {f.name: None for f in dataclasses.fields(EpisodeResult)}
    start = tasks.load_tasks("FloorPlan1").targets[0]
    result = EpisodeResult(**{**fields, "kitchen": "FloorPlan1", "target": start.object_id, "start": 0,
                              "stopped": True, "last_view_shows_target": True, "success": False})  # fmt: skip
    [scored] = evaluate.scored_visible([result])
    assert calls == ["destination", "visible"] and scored.success


def test_collisions_count_failed_moves_only(make_env, graph):
    env = make_env()
    closed = np.arange(graph.n_states) < graph.n_closed
    blocked = np.flatnonzero(closed & ~graph.ok[:, MOVE_AHEAD] & (graph.pitch == 0))
    assert len(blocked) > 0
    start = int(blocked[0])
    env.reset(options={"episodes": [episode(APPLE, start)]})
    [(reward, term, trunc, info)] = run(env, [MOVE_AHEAD])
    assert info["collisions"] == 1 and info["state"] == start
    assert reward == pytest.approx(STEP_REWARD) and not term and not trunc
    assert info["path_length"] == 1  # a failed move is still an action
    [(_, _, _, info)] = run(env, [MOVE_AHEAD])
    assert info["collisions"] == 2
    # every failed move of the four counts; rotations and successful moves do not
    for move in (MOVE_AHEAD, MOVE_BACK, MOVE_RIGHT, MOVE_LEFT):
        failing = np.flatnonzero(closed & ~graph.ok[:, move])
        passing = np.flatnonzero(closed & graph.ok[:, move])
        for s, expected in ((failing[0], 1), (passing[0], 0)):
            env.reset(options={"episodes": [episode(APPLE, s)]})
            [(_, _, _, info)] = run(env, [move])
            assert info["collisions"] == expected, (ACTIONS[move], expected)
    env.reset(options={"episodes": [episode(APPLE, start)]})
    steps = run(env, [ROTATE_RIGHT, ROTATE_LEFT, LOOK_DOWN, LOOK_UP])
    assert [s[3]["collisions"] for s in steps] == [0, 0, 0, 0]


def test_a_failed_look_is_not_a_collision(make_env, graph):
    env = make_env()
    cell, heading = graph.pose(0).cell, graph.pose(0).heading
    start = graph.state_of(Pose(cell, heading, -30))
    assert graph.pitch[start] == -30 and not graph.ok[start, LOOK_UP]
    env.reset(options={"episodes": [episode(APPLE, start)]})
    [(reward, term, _, info)] = run(env, [LOOK_UP])
    assert info["state"] == start  # it failed
    assert info["collisions"] == 0
    assert reward == pytest.approx(STEP_REWARD) and not term
    bottom = graph.state_of(Pose(cell, heading, 60))
    assert not graph.ok[bottom, LOOK_DOWN]
    env.reset(options={"episodes": [episode(APPLE, bottom)]})
    [(_, _, _, info)] = run(env, [LOOK_DOWN])
    assert info["state"] == bottom and info["collisions"] == 0


def test_a_failed_open_is_not_a_collision(make_env, graph):
    env = make_env()
    closed = np.arange(graph.n_states) < graph.n_closed
    nothing_to_open = int(np.flatnonzero(closed & ~graph.ok[:, OPEN])[0])
    env.reset(options={"episodes": [episode(APPLE, nothing_to_open)]})
    [(_, _, _, info)] = run(env, [OPEN])
    assert info["state"] == nothing_to_open and info["collisions"] == 0


@pytest.mark.parametrize("max_steps", [1, 3, 7])
def test_episodes_are_truncated_at_max_steps(make_env, tasks, max_steps):
    env = make_env(n_agents=2)
    start = tasks.target(APPLE).starts[0]
    env.reset(options={"episodes": [episode(APPLE, start, max_steps), episode(APPLE, start, 100)]})
    for t in range(1, max_steps + 1):
        _, rewards, terms, truncs, infos = env.step(dict.fromkeys(env.agents, ROTATE_RIGHT))
        assert rewards[A0] == pytest.approx(STEP_REWARD)
        assert terms[A0] is False
        assert truncs[A0] is (t == max_steps)
        assert infos[A0]["episode_length"] == t
        assert infos[A0]["success"] is False
        assert truncs["navigator_1"] is False
    assert env.agents == ["navigator_1"]


def test_the_training_max_steps_applies_without_fixed_episodes(make_env):
    env = make_env(n_agents=2, max_steps=4)
    env.reset(seed=5)
    for t in range(1, 5):
        _, _, terms, truncs, _ = env.step(dict.fromkeys(env.agents, ROTATE_LEFT))
        assert truncs == dict.fromkeys(env.possible_agents, t == 4)
        assert not any(terms.values())
    assert env.agents == []


def test_a_stop_on_the_last_step_terminates_rather_than_truncates(make_env, egg_start):
    env = make_env(success_rule="visible")  # the egg in view from the open fridge, anywhere
    env.reset(options={"episodes": [episode(EGG, egg_start, max_steps=2)]})
    (_, _, trunc1, _), (_, term2, trunc2, info2) = run(env, [OPEN, STOP])
    assert not trunc1
    assert term2 and not trunc2 and info2["success"]


# ------------------------------------------------------------------------------------------------
# Auto-close


def test_any_action_but_stop_closes_the_receptacle(make_env, graph, egg_start):
    env = make_env(stop_ends=False)
    open_state = int(graph.next_state[egg_start, OPEN])
    fridge = graph.world.index(FRIDGE)
    for a in range(len(ACTIONS)):
        env.reset(options={"episodes": [episode(EGG, egg_start)]})
        [(_, _, _, info)] = run(env, [OPEN])
        assert info["state"] == open_state and graph.opened[open_state] == fridge
        [(_, _, _, info)] = run(env, [a])
        if a == STOP:
            assert info["state"] == open_state  # Stop keeps it open (and here succeeds)
        elif a == OPEN:
            assert info["state"] == open_state  # closes and reopens the same fridge
        else:
            assert graph.opened[info["state"]] == -1, ACTIONS[a]
            assert info["state"] == graph.next_state[egg_start, a]  # as from the closed twin
            assert info["last_view_shows_target"] is False


# ------------------------------------------------------------------------------------------------
# Determinism


def _trajectory(env, seed, n_steps=40):
    observations, infos = env.reset(seed=seed)
    record = [(sorted(infos.items()), {a: o["view"].tobytes() for a, o in observations.items()})]
    rng = np.random.default_rng(123)
    for _ in range(n_steps):
        if not env.agents:
            break
        actions = {a: int(rng.integers(0, STOP)) for a in env.agents}  # never Stop
        observations, rewards, terms, truncs, infos = env.step(actions)
        record.append((sorted(infos.items()), sorted(rewards.items()), terms, truncs))
    return record


def test_same_seed_same_episodes(make_env):
    a = make_env(n_agents=4, targets="all")
    b = make_env(n_agents=4, targets="all")
    assert _trajectory(a, 7) == _trajectory(b, 7)
    # reseeding the same env repeats it too
    assert _trajectory(a, 7) == _trajectory(a, 7)


def test_different_seeds_different_episodes(make_env):
    env = make_env(n_agents=4, targets="all")

    def episodes(seed):
        _, infos = env.reset(seed=seed)
        return [(i["target"], i["state"]) for i in infos.values()]

    assert episodes(1) == episodes(1)
    draws = {tuple(episodes(seed)) for seed in range(5)}
    assert len(draws) == 5


def test_unseeded_resets_continue_the_generator(make_env):
    env = make_env(n_agents=2)
    _, first = env.reset(seed=0)
    _, second = env.reset()
    assert [i["state"] for i in first.values()] != [i["state"] for i in second.values()] or [
        i["target"] for i in first.values()
    ] != [i["target"] for i in second.values()]


@pytest.mark.parametrize("target_set", ["seen", "unseen", "all"])
def test_training_targets_come_from_the_chosen_set(make_env, tasks, target_set):
    env = make_env(n_agents=4, targets=target_set)
    wanted = {t.object_id for t in tasks.targets if target_set == "all" or t.seen == (target_set == "seen")}
    drawn = set()
    for seed in range(10):
        _, infos = env.reset(seed=seed)
        drawn |= {i["target"] for i in infos.values()}
    assert drawn <= wanted
    assert len(drawn) > 1


def test_training_targets_from_a_list(make_env):
    env = make_env(n_agents=3, targets=[EGG])
    _, infos = env.reset(seed=0)
    assert {i["target"] for i in infos.values()} == {EGG}
    assert all(i["target_kind"] == "actionable" for i in infos.values())


# ------------------------------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"success_rule": "nearby"}, "unknown success_rule 'nearby'"),
        ({"targets": "some"}, "unknown target set 'some'"),
        ({"targets": ["Teapot|1"]}, "Teapot|1"),
        ({"targets": []}, "no"),
        ({"render_mode": "human"}, "unknown render_mode 'human'"),
        ({"n_agents": 0}, "n_agents must be a whole number in 1..100,000"),
        ({"n_agents": 2.0}, "n_agents must be a whole number in 1..100,000"),
        ({"n_agents": 10**7}, "n_agents must be a whole number in 1..100,000, not 10000000"),
        ({"max_steps": 0}, "max_steps must be a whole number in 1..1,000,000"),
        ({"max_steps": -5}, "max_steps must be a whole number in 1..1,000,000"),
        ({"max_steps": 2.7}, "max_steps must be a whole number in 1..1,000,000"),
        ({"max_steps": True}, "max_steps must be a whole number in 1..1,000,000"),
        ({"max_steps": 2**63}, "max_steps must be a whole number in 1..1,000,000"),
        ({"view_size": 0}, "view_size must be a whole number of pixels in 8..256, not 0"),
        ({"view_size": 10**6}, "view_size must be a whole number of pixels in 8..256"),
        ({"view_size": 84.0}, "view_size must be a whole number of pixels"),
        # as the Gymnasium envs: a flag is True or False ("no" and "false" are true strings)
        ({"features": "no"}, "features must be True or False, not 'no'"),
        ({"autoreset": "no"}, "autoreset must be True or False, not 'no'"),
        ({"stop_ends": "false"}, "stop_ends must be True or False, not 'false'"),
        ({"privileged": 1}, "privileged must be True or False, not 1"),
        ({"tasks": "x"}, "tasks must be a KitchenTasks"),
    ],
)
def test_bad_options_are_reported(make_env, kwargs, message):
    with pytest.raises(EnvError, match=message.replace("|", r"\|")):
        make_env(**kwargs)


@pytest.mark.parametrize("seed", [-1, "0", 1.5, True])
def test_a_reset_seed_that_is_not_a_whole_number_from_0_is_refused(make_env, seed):
    with pytest.raises(EnvError, match="seed must be a whole number >= 0 or None"):
        make_env().reset(seed=seed)


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ({"target": "Teapot|1", "start": 0}, "unknown target"),
        ({"start": 0}, "missing key 'target'"),
        ({"target": APPLE}, "missing key 'start'"),
        ({"target": APPLE, "start": -1}, "out of range"),
        ({"target": APPLE, "start": 10**6}, "out of range"),
        ({"target": APPLE, "start": 0, "max_steps": 0}, "out of range"),
        ({"target": APPLE, "start": 0, "max_steps": -5}, "out of range"),
        ({"target": APPLE, "start": 0, "max_steps": 2.7}, "must be integers"),
        ({"target": APPLE, "start": 0, "max_steps": True}, "must be integers"),
        ({"target": APPLE, "start": "nowhere"}, "bad episode"),
        ({"target": APPLE, "start": None}, "bad episode"),
        ("not a dict", "bad episode"),
    ],
)
def test_bad_episodes_are_reported(make_env, bad, message):
    env = make_env()
    with pytest.raises(EnvError, match=message) as info:
        env.reset(options={"episodes": [bad]})
    assert "bad episode" in str(info.value)


def test_unknown_reset_options_and_a_step_before_reset_are_refused(make_env, tasks):
    """A typo ("episode" for "episodes") is an error, not a random episode; stepping or reading the
    arrays before reset() is one line, not an AttributeError."""
    env = make_env()
    for typo in ("episode", "Episodes", "episdoes"):
        with pytest.raises(EnvError, match=rf"unknown reset options \['{typo}'\]; known: episodes"):
            env.reset(options={typo: [{"target": APPLE, "start": 0}]})
    # any other key: a warning naming it (PettingZoo's API test resets with {"options": 1})
    with pytest.warns(UnknownOptionWarning, match=r"ignores unknown options \['colour'\]"):
        env.reset(options={"colour": "red"})
    env = make_env()
    for call in (lambda: env.step({"navigator_0": 0}), env.observation_arrays, lambda: env.step_arrays([0])):
        with pytest.raises(EnvError, match="before reset"):
            call()


def test_observations_are_read_only_so_agents_cannot_change_each_others(make_env):
    """The dict observations' arrays are views of tables the agents share: read-only, so an in-place
    write is an error rather than another agent's observation changed for the rest of the episode."""
    env = make_env(n_agents=2, features=True)
    observations, _ = env.reset(seed=0)
    for key in ("features", "target_features", "view", "target", "view_objects", "target_objects"):
        with pytest.raises(ValueError, match="read-only"):
            observations["navigator_0"][key][...] = 0


def test_unreachable_start_is_reported(make_env, tasks):
    # every state of FloorPlan1 reaches every target, so make one unreachable in this env's tables
    assert (tasks.distances(tasks.target(EGG)) >= 0).all()
    env = make_env(targets=[EGG])
    start = tasks.target(EGG).starts[0]
    env._tables.dist = env._tables.dist.copy()
    env._tables.dist[env._target_row[EGG], start] = -1
    with pytest.raises(EnvError, match="the goal cannot be reached from the start"):
        env.reset(options={"episodes": [episode(EGG, start)]})


def test_more_episodes_than_agents_is_reported(make_env, tasks):
    env = make_env(n_agents=1)
    start = tasks.target(APPLE).starts[0]
    with pytest.raises(EnvError, match="2 episodes for 1 agents"):
        env.reset(options={"episodes": [episode(APPLE, start)] * 2})


def test_bad_actions_are_reported(make_env):
    env = make_env(n_agents=2)
    env.reset(seed=0)
    with pytest.raises(EnvError, match="no action for live agent"):
        env.step({A0: 0})
    with pytest.raises(EnvError, match="integers 0..9"):
        env.step({A0: 0, "navigator_1": 10})
    with pytest.raises(EnvError, match="integers 0..9"):
        env.step({A0: -1, "navigator_1": 0})


# ------------------------------------------------------------------------------------------------
# Rendering


def test_render_rgb_array(make_env, tasks):
    env = make_env(n_agents=2, render_mode="rgb_array")
    with pytest.raises(EnvError, match="before reset"):
        env.render()
    env.reset(seed=0)
    image = env.render()
    assert isinstance(image, np.ndarray)
    assert image.shape == (400, 400, 3) and image.dtype == np.uint8
    assert image.std() > 0  # a picture, not a blank
    env.step(dict.fromkeys(env.agents, MOVE_AHEAD))
    env.step(dict.fromkeys(env.agents, ROTATE_RIGHT))
    after = env.render()
    assert after.shape == (400, 400, 3)


def test_render_without_a_mode_returns_none(make_env):
    env = make_env()
    env.reset(seed=0)
    assert env.render() is None


def test_a_dropped_env_is_freed(make_env):
    """The spaces are plain dict lookups: no functools.cache on methods holding every env alive."""
    import gc
    import weakref

    env = make_env(n_agents=2)
    env.action_space("navigator_0")
    env.observation_space("navigator_1")
    ref = weakref.ref(env)
    del env
    gc.collect()
    assert ref() is None


def test_the_array_face_steps_as_the_dict_face(make_env, tasks):
    """observation_arrays / info_arrays / step_arrays (the batched evaluation path) give, agent for agent,
    the dict API's observations, infos, rewards and terminations, and the same agents leave."""
    episodes = [episode(t.object_id, s, max_steps=30) for t in tasks.targets[:4] for s in t.starts[:3]]
    dict_env = make_env(n_agents=len(episodes), features=True)
    array_env = make_env(n_agents=len(episodes), features=True)
    observations, infos = dict_env.reset(options={"episodes": episodes})
    array_env.reset(options={"episodes": episodes})
    rng = np.random.default_rng(0)
    while dict_env.agents:
        agents = list(dict_env.agents)
        assert array_env.agents == agents
        batch, shown = array_env.observation_arrays(), array_env.info_arrays()
        assert set(batch) == set(observations[agents[0]]) and "state" not in shown
        for key in batch:
            assert np.array_equal(batch[key], np.stack([observations[a][key] for a in agents]))
        for key, column in shown.items():
            assert list(column) == [infos[a][key] for a in agents], key
        actions = rng.integers(0, len(ACTIONS), len(agents))
        observations, rewards, terms, truncs, infos = dict_env.step(dict(zip(agents, actions.tolist())))
        r, term, trunc, step_infos = array_env.step_arrays(actions)
        assert r.tolist() == [rewards[a] for a in agents]
        assert term.tolist() == [terms[a] for a in agents] and trunc.tolist() == [truncs[a] for a in agents]
        for key, column in step_infos.items():
            assert list(column) == [infos[a][key] for a in agents], key
    assert not array_env.agents
    with pytest.raises(EnvError, match="integers"):
        array_env.reset(options={"episodes": episodes})
        array_env.step_arrays(np.zeros(3))


@pytest.mark.parametrize(
    ("episodes", "message"),
    [
        (5, "options\\['episodes'\\] must be a list of episodes"),
        ("abc", "must be a list of episodes .* not str"),
        ([{"target": APPLE, "start": 0, "max_steps": 2**63}], "out of range"),
    ],
)
def test_fixed_episodes_that_are_no_list_or_out_of_range_are_refused(make_env, episodes, message):
    with pytest.raises(EnvError, match=message):
        make_env(n_agents=1).reset(options={"episodes": episodes})
