"""The vector env stage: Navigators step exactly as the PettingZoo env, training starts and the
curriculum, and the Gymnasium faces (registered ids, check_env, make_vec, same-step autoreset, fresh
arrays, nothing privileged, errors)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import kgnavbench  # noqa: F401 - registers the Gymnasium ids
from kgnavbench import vecenv
from kgnavbench.env import parallel_env
from kgnavbench.graph import STOP


@pytest.fixture(scope="module")
def space(floorplan1_tasks):
    return vecenv.build_space(["FloorPlan1"], "all", "destination")


# ----------------------------------------------------------------------------------------------------
# the navigators step exactly as the env


@pytest.mark.parametrize("rule", ["destination", "visible"])
def test_navigators_give_the_envs_episodes(floorplan1_tasks, rule):
    """The same fixed episodes and the same random actions through the PettingZoo env and through
    Navigators (array gathers): identical states, rewards, terminations and episode statistics."""
    tasks = floorplan1_tasks
    space = vecenv.build_space(["FloorPlan1"], "all", rule)
    rows = {t: r for r, t in enumerate(space.target_ids)}
    episodes = [
        {"target": t.object_id, "start": s, "max_steps": 60} for t in tasks.targets[:6] for s in t.starts[:3]
    ]
    env = parallel_env(kitchen="FloorPlan1", n_agents=len(episodes), targets="all", success_rule=rule)
    _, infos = env.reset(options={"episodes": episodes})
    agents = list(env.agents)
    nav = vecenv.Navigators(space, np.zeros(len(episodes), np.int64))
    nav.begin(
        np.arange(len(episodes)),
        np.array([rows[e["target"]] for e in episodes]),
        np.array([e["start"] for e in episodes]),
        60,
    )
    rng = np.random.default_rng(0)
    live = np.ones(len(episodes), bool)
    steps = 0
    while env.agents:
        # Stop rarely, so that episodes run long and some end at the cap
        actions = np.where(rng.random(len(episodes)) < 0.03, STOP, rng.integers(0, STOP, len(episodes)))
        idx = np.flatnonzero(live)
        _, rewards, terminations, truncations, infos = env.step({agents[i]: int(actions[i]) for i in idx})
        r, term, trunc = nav.step(actions[idx], idx)
        for j, i in enumerate(idx):
            a, info = agents[i], infos[agents[i]]
            assert rewards[a] == pytest.approx(r[j])
            assert (terminations[a], truncations[a]) == (bool(term[j]), bool(trunc[j]))
            assert info["state"] == nav.state[i] - space.offsets[0]
            assert info["success"] == nav.success[i]
            assert info["path_length"] == nav.path[i]
            assert info["collisions"] == nav.collisions[i]
            assert info["episode_length"] == nav.steps[i]
        live[idx[term | trunc]] = False
        steps += len(idx)
    assert not live.any() and steps > 200
    assert nav.collisions.sum() > 0


def test_training_starts_are_the_envs(space, floorplan1_tasks):
    """Navigators.draw starts where the env would: pitch 0, target out of view, >= 10 actions away."""
    nav = vecenv.Navigators(space, np.zeros(500, np.int64))
    nav.draw(np.arange(500), np.random.default_rng(1), 5000)
    graph = floorplan1_tasks.graph
    assert (graph.pitch[nav.state] == 0).all()
    assert not space.visible[nav.target, nav.state].any()
    assert (space.dist[nav.target, nav.state] >= 10).all()
    assert len(set(nav.target.tolist())) > 5


def test_curriculum_starts_near_the_destination_then_ever_farther(space, floorplan1_tasks):
    """reach 0: every episode starts as near its destination as a start can (on it, where it is
    closed at pitch 0); reach r: within r actions, at pitch 0 with no receptacle open, each distance
    0..r about equally frequent."""
    graph = floorplan1_tasks.graph
    nav = vecenv.Navigators(space, np.zeros(3000, np.int64))
    nav.draw(np.arange(3000), np.random.default_rng(2), 200, reach=0)
    startable = space.closed & (graph.pitch == 0)
    nearest = np.where(startable, space.dist, 10**6).min(1)
    assert (space.dist[nav.target, nav.state] == nearest[nav.target]).all()
    assert (nav.state == space.destination[nav.target]).any()
    nav.draw(np.arange(3000), np.random.default_rng(3), 200, reach=6)
    dist = space.dist[nav.target, nav.state]
    assert (graph.pitch[nav.state] == 0).all() and space.closed[nav.state].all()
    counts = np.bincount(dist[nearest[nav.target] == 0], minlength=7)
    assert dist.max() == 6 and counts.min() > counts.sum() / 7 * 0.7, counts
    assert (nav.cap == 200).all() and nav.arrived[dist == 0].all() and not nav.arrived[dist > 0].any()


# ----------------------------------------------------------------------------------------------------
# the Gymnasium faces


def test_registered_single_env_passes_gymnasiums_checker(floorplan1_tasks):
    env = gym.make("kgnavbench/FloorPlan1-v0")
    check_env(env.unwrapped, skip_render_check=True)
    observation, info = env.reset(seed=3)
    assert env.observation_space.contains(observation)
    assert info["kitchen"] == "FloorPlan1" and info["target"]
    assert "state" not in info and "expert_action" not in info
    again, _ = env.reset(seed=3)
    assert all(np.array_equal(observation[k], again[k]) for k in observation)
    # fresh, writable arrays: the next step does not change what the last one returned
    before = {k: v.copy() for k, v in observation.items()}
    for action in (0, 4, 0, 5):
        following, *_ = env.step(action)
        assert all(v.flags.writeable for v in following.values())
    assert all(np.array_equal(before[k], observation[k]) for k in before)


def test_single_env_plays_a_fixed_episode_to_success(floorplan1_tasks):
    """reset(options={"target", "start"}) starts a task-file episode; the BFS expert's actions reach
    success with the episode's shortest path and +10 at the end."""
    target = floorplan1_tasks.targets[0]
    start = target.starts[0]
    env = vecenv.NavigationGymEnv("FloorPlan1", targets="all")
    observation, info = env.reset(options={"target": target.object_id, "start": start})
    assert info["target"] == target.object_id
    dist = floorplan1_tasks.distances(target, "destination")
    from kgnavbench.graph import expert_actions

    expert = expert_actions(floorplan1_tasks.graph.next_state, dist)
    state, total, steps = start, 0.0, 0
    while True:
        action = int(expert[state]) if dist[state] > 0 else STOP
        observation, reward, terminated, truncated, info = env.step(action)
        total += reward
        steps += 1
        state = floorplan1_tasks.graph.next_state[state, action] if action != STOP else state
        if terminated or truncated:
            break
    assert terminated and info["success"] and reward == pytest.approx(10.0 - 0.01)
    assert info["path_length"] == info["shortest_path"] == dist[start]
    assert info["episode_length"] == steps == dist[start] + 1
    with pytest.raises(vecenv.VecEnvError, match="not a target"):
        env.reset(options={"target": "Nothing|1", "start": 0})
    with pytest.raises(vecenv.VecEnvError, match="action"):
        env.step(12)


def test_make_vec_gives_the_batched_env_with_same_step_autoreset(floorplan1_tasks):
    envs = gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=16)
    assert isinstance(envs.unwrapped, vecenv.NavigationVectorEnv) and envs.num_envs == 16
    observations, infos = envs.reset(seed=0)
    assert envs.observation_space.contains(observations)
    assert observations["features"].shape == (16, 512) and observations["features"].dtype == np.float32
    assert list(infos["kitchen"]) == ["FloorPlan1"] * 16
    rng = np.random.default_rng(0)
    finished = successes = 0
    for _ in range(300):
        previous = {k: v.copy() for k, v in observations.items()}
        actions = np.where(rng.random(16) < 0.05, STOP, rng.integers(0, STOP, 16))
        returned = observations
        observations, rewards, terminations, truncations, infos = envs.step(actions)
        assert all(np.array_equal(previous[k], returned[k]) for k in previous)  # fresh arrays
        assert rewards.shape == (16,) and terminations.dtype == bool
        done = terminations | truncations
        if done.any():
            assert (infos["_final_obs"] == done).all() and (infos["_final_info"] == done).all()
            for i in np.flatnonzero(done):
                assert envs.single_observation_space.contains(infos["final_obs"][i])
            final = infos["final_info"]
            assert (final["episode_length"][done] >= 1).all()
            assert (final["success"][done] == (rewards[done] > 5)).all()
            finished += int(done.sum())
            successes += int(final["success"][done].sum())
        assert "state" not in infos and "expert_action" not in infos
    assert finished > 16


def test_vector_env_without_autoreset_waits_for_reset_mask(floorplan1_tasks):
    """gymnasium's DISABLED mode, as the trainer steps it: the ending step returns the episode's last
    observation and its final_info; the finished sub-envs refuse to step until reset by mask, and
    only they get new episodes; `reach` draws curriculum starts."""
    from gymnasium.vector import AutoresetMode

    envs = vecenv.NavigationVectorEnv(num_envs=4, kitchens="FloorPlan1", autoreset=False, max_steps=3)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.DISABLED
    envs.reset(seed=0)
    for _ in range(2):
        _, _, terminated, truncated, infos = envs.step(np.full(4, STOP - 1, np.int64))  # LookDown
        assert "final_info" not in infos
    observations, _, terminated, truncated, infos = envs.step(np.full(4, STOP - 1, np.int64))
    assert truncated.all() and "final_obs" not in infos and (infos["final_info"]["episode_length"] == 3).all()
    before = envs.navigators.state.copy()
    assert np.array_equal(observations["view_objects"], envs.space.objects[before])  # the last view
    with pytest.raises(vecenv.VecEnvError, match="reset_mask"):
        envs.step(np.zeros(4, np.int64))
    mask = np.array([True, False, True, False])
    with pytest.raises(vecenv.VecEnvError, match="reset_mask must be 4 bools"):
        envs.reset(options={"reset_mask": mask.astype(int)})
    with pytest.raises(vecenv.VecEnvError, match="unknown reset options"):
        envs.reset(options={"mask": mask})
    envs.reset(options={"reset_mask": mask, "reach": 0})
    nav = envs.navigators
    assert (nav.steps[mask] == 0).all() and (nav.steps[~mask] == 3).all()
    # reach 0: the nearest starts the curriculum has (one action from the destination here)
    assert (envs.space.dist[nav.target[mask], nav.state[mask]] <= 1).all()
    with pytest.raises(vecenv.VecEnvError, match="reset them first"):
        envs.step(np.zeros(4, np.int64))  # sub-envs 1 and 3 still wait
    envs.reset(options={"reset_mask": ~mask})
    envs.step(np.zeros(4, np.int64))


def test_vector_env_over_a_split_spreads_its_kitchens(floorplan1_tasks):
    envs = vecenv.NavigationVectorEnv(num_envs=6, kitchens=["FloorPlan1", "FloorPlan2"], targets="all")
    _, infos = envs.reset(seed=1)
    assert list(infos["kitchen"]) == ["FloorPlan1", "FloorPlan2"] * 3
    a, _ = envs.reset(seed=1)
    b, _ = envs.reset(seed=1)
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_vector_env_errors_name_the_problem(floorplan1_tasks):
    with pytest.raises(vecenv.VecEnvError, match="FloorPlan99"):
        vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan99")
    with pytest.raises(vecenv.VecEnvError, match="target set"):
        vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan1", targets="unseen")
    with pytest.raises(vecenv.VecEnvError, match="FloorPlan21 has no seen targets .*targets='all'"):
        vecenv.NavigationGymEnv("FloorPlan21", targets="seen")
    with pytest.raises(vecenv.VecEnvError, match="num_envs"):
        vecenv.NavigationVectorEnv(num_envs=0, kitchens="FloorPlan1")
    envs = vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan1")
    envs.reset(seed=0)
    with pytest.raises(vecenv.VecEnvError, match="2 integers"):
        envs.step(np.zeros(3, np.int64))
    with pytest.raises(vecenv.VecEnvError, match="0..9"):
        envs.step(np.array([0, 10]))


def test_every_kitchen_and_split_has_an_id_and_registering_loads_no_torch():
    import subprocess
    import sys

    from gymnasium.envs.registration import registry

    from kgnavbench.kitchens import KITCHEN_NAMES

    for name in (*KITCHEN_NAMES, *vecenv.SPLIT_NAMES):
        assert f"kgnavbench/{name}-v0" in registry
    # `import kgnavbench` (every command line start) registers them without importing torch
    code = "import sys, kgnavbench, kgnavbench.cli; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
