"""The vector env stage: Navigators step exactly as the PettingZoo env, training starts and the
curriculum, and the Gymnasium faces (registered ids, check_env, make_vec, same-step autoreset, fresh
arrays, nothing privileged, errors)."""

from __future__ import annotations

import subprocess
import sys

import cv2
import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import kgnavbench  # noqa: F401 - registers the Gymnasium ids
from kgnavbench import gymenv, vecenv
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
    env = parallel_env(
        kitchen="FloorPlan1", n_agents=len(episodes), targets="all", success_rule=rule, privileged=True
    )
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
    env = gymenv.NavigationGymEnv("FloorPlan1", targets="all")
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


@pytest.mark.parametrize("mode", ["next_step", "same_step"])
def test_make_vec_gives_the_batched_env_in_either_autoreset_mode(floorplan1_tasks, mode):
    """gymnasium's NEXT_STEP (the default, what its vector wrappers expect): the step that ends an
    episode returns its last observation; the next step starts the next episode, ignoring the action,
    with reward 0. SAME_STEP: the ending step returns the next episode's first observation and the last
    one in final_obs. Either way final_info (on every step, masks False where nothing ended) holds the
    ended episodes' success and lengths."""
    from gymnasium.vector import AutoresetMode

    envs = gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=16, autoreset_mode=mode)
    assert isinstance(envs.unwrapped, vecenv.NavigationVectorEnv) and envs.num_envs == 16
    assert envs.metadata["autoreset_mode"] == AutoresetMode[mode.upper()]
    assert envs.spec.max_episode_steps == vecenv.TRAINING_MAX_STEPS
    observations, infos = envs.reset(seed=0)
    assert envs.observation_space.contains(observations)
    assert observations["features"].shape == (16, 512) and observations["features"].dtype == np.float32
    assert list(infos["kitchen"]) == ["FloorPlan1"] * 16
    rng = np.random.default_rng(0)
    finished = successes = restarted = 0
    ended = np.zeros(16, bool)
    for _ in range(300):
        previous = {k: v.copy() for k, v in observations.items()}
        steps_before = envs.unwrapped.navigators.steps.copy()
        actions = np.where(rng.random(16) < 0.05, STOP, rng.integers(0, STOP, 16))
        returned = observations
        observations, rewards, terminations, truncations, infos = envs.step(actions)
        assert all(np.array_equal(previous[k], returned[k]) for k in previous)  # fresh arrays
        assert rewards.shape == (16,) and terminations.dtype == bool
        done = terminations | truncations
        stepped = ~done if mode == "same_step" else ~ended  # (same step: the ended ones start again)
        assert (envs.unwrapped.navigators.steps == steps_before + 1)[stepped].all()
        if mode == "next_step" and ended.any():  # last step's ended ones: a new episode, action ignored
            assert (rewards[ended] == 0).all() and not done[ended].any()
            assert (envs.unwrapped.navigators.steps[ended] == 0).all()
            restarted += int(ended.sum())
        assert (infos["_final_info"] == done).all()
        if done.any():
            if mode == "same_step":
                assert (infos["_final_obs"] == done).all()
                for i in np.flatnonzero(done):
                    assert envs.single_observation_space.contains(infos["final_obs"][i])
            else:
                assert "final_obs" not in infos
            final = infos["final_info"]
            assert (final["episode_length"][done] >= 1).all()
            assert (final["success"][done] == (rewards[done] > 5)).all()
            finished += int(done.sum())
            successes += int(final["success"][done].sum())
        ended = done
        assert "state" not in infos and "expert_action" not in infos
    assert finished > 16 and (restarted > 16 or mode == "same_step")


def test_gymnasiums_vector_wrappers_and_sync_vectorization_take_the_envs(floorplan1_tasks):
    """The NEXT_STEP vector env under gymnasium's own vector wrappers (normalising observations and
    rewards, episode statistics), and make_vec's sync mode with a wrapper on each single env."""
    from gymnasium.wrappers.vector import NormalizeObservation, NormalizeReward, RecordEpisodeStatistics

    envs = gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=4, observation="box", max_steps=20)
    envs = RecordEpisodeStatistics(NormalizeReward(NormalizeObservation(envs)))
    envs.reset(seed=0)
    seen_episode = False
    for _ in range(45):
        observations, _, _, _, infos = envs.step(envs.action_space.sample())
        assert observations.shape == (4, 1274) and np.isfinite(observations).all()
        seen_episode |= "episode" in infos
    assert seen_episode
    synced = gym.make_vec(
        "kgnavbench/FloorPlan1-v0",
        num_envs=2,
        vectorization_mode="sync",
        wrappers=[gym.wrappers.FlattenObservation],
        max_steps=10,
    )
    observations, _ = synced.reset(seed=0)
    assert observations.shape == (2, 2 * 512 + 2 * 125)


def test_the_envs_take_the_training_protocol_as_keywords(floorplan1_tasks):
    """stop_ends, max_steps (spec.max_episode_steps) and curriculum_steps on the single and vector
    envs: the curriculum's reach grows from 0 to 25 over the env's first N steps, as the trainer's;
    unknown keywords, reset options and bad values are refused with one line."""
    env = gym.make("kgnavbench/FloorPlan1-v0", stop_ends=False, max_steps=200, curriculum_steps=1000)
    assert env.spec.max_episode_steps == 200 and env.unwrapped.max_steps == 200
    env.reset(seed=0)
    dist = env.unwrapped.space.dist
    nav = env.unwrapped.navigators
    assert env.unwrapped.reach() == 0 and dist[nav.target[0], nav.state[0]] <= 1
    _, reward, terminated, _, _ = env.step(STOP)  # a Stop that does not succeed: a no-op
    assert not terminated or reward > 5
    for _ in range(499):
        env.step(0)
    assert env.unwrapped.reach() == 12  # 25 * 500 / 1000
    for _ in range(500):
        env.step(0)
    assert env.unwrapped.reach() is None  # over: the training starts, 10-25 actions away
    env.reset()
    assert dist[nav.target[0], nav.state[0]] >= 10
    # gym.make(id, max_episode_steps=N): gymnasium's TimeLimit truncates there
    short = gym.make("kgnavbench/FloorPlan1-v0", max_episode_steps=7)
    assert short.spec.max_episode_steps == 7
    short.reset(seed=0)
    for i in range(7):
        _, _, terminated, truncated, _ = short.step(6 if i % 2 else 7)  # LookUp, LookDown
    assert truncated and not terminated
    # the vector env: the curriculum counts every sub-env's steps (frames, as the trainer's)
    envs = vecenv.NavigationVectorEnv(num_envs=10, kitchens="FloorPlan1", curriculum_steps=100, max_steps=50)
    envs.reset(seed=0)
    assert envs.reach() == 0
    for _ in range(5):
        envs.step(np.zeros(10, np.int64))
    assert envs.reach() == 12
    # refused, each in one line
    with pytest.raises(TypeError, match="nope"):
        gym.make("kgnavbench/FloorPlan1-v0", nope=1)
    for bad in (0, -5, 2.7, True, "10"):
        with pytest.raises(vecenv.VecEnvError, match="max_steps must be a whole number in 1..1,000,000"):
            gymenv.NavigationGymEnv("FloorPlan1", max_steps=bad)
        with pytest.raises(vecenv.VecEnvError, match="max_steps must be a whole number in 1..1,000,000"):
            env.reset(options={"target": env.unwrapped.space.target_ids[0], "start": 0, "max_steps": bad})
    with pytest.raises(vecenv.VecEnvError, match=r"unknown reset options \['episode'\]"):
        env.reset(options={"episode": 3})
    with pytest.raises(vecenv.VecEnvError, match="curriculum_steps"):
        vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan1", curriculum_steps=-1)
    with pytest.raises(vecenv.VecEnvError, match="autoreset_mode"):
        vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan1", autoreset_mode="sometimes")
    with pytest.raises(vecenv.VecEnvError, match="stop_ends must be True or False"):
        gymenv.NavigationGymEnv("FloorPlan1", stop_ends="no")
    with pytest.raises(vecenv.VecEnvError, match="step\\(\\) before reset"):
        gymenv.NavigationGymEnv("FloorPlan1").step(0)
    with pytest.raises(vecenv.VecEnvError, match="step\\(\\) before reset"):
        vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan1").step(np.zeros(2, np.int64))


def test_the_flat_box_observation_and_readable_bounds(floorplan1_tasks):
    """observation="box": one float32 vector, BOX_PARTS in order (features, view_objects,
    target_features, target_objects), the dict's numbers; the features' bounds are -inf..inf, so
    printing the space prints a line, not a thousand numbers."""
    env = gymenv.NavigationGymEnv("FloorPlan1", observation="box")
    plain = gymenv.NavigationGymEnv("FloorPlan1")
    box, _ = env.reset(seed=3)
    d, _ = plain.reset(seed=3)
    assert box.shape == (1274,) and box.dtype == np.float32 and env.observation_space.contains(box)
    expected = np.concatenate([d[k].astype(np.float32) for k in vecenv.BOX_PARTS])
    assert np.array_equal(box, expected)
    assert len(str(plain.observation_space)) < 400, str(plain.observation_space)
    assert "inf" in str(plain.observation_space["features"])


def test_render_shows_the_view_and_target_beside_the_map(floorplan1_tasks):
    """render(): the egocentric view and the target image above the top-down map, at render_fps;
    the vector env renders its first sub-env."""
    env = gym.make("kgnavbench/FloorPlan1-v0", render_mode="rgb_array")
    assert env.metadata["render_fps"] > 0
    env.reset(seed=0)
    picture = env.render()
    nav = env.unwrapped.navigators
    view = np.asarray(floorplan1_tasks.graph.views[int(nav.state[0])])
    assert picture.ndim == 3 and picture.shape[2] == 3 and picture.dtype == np.uint8
    assert picture.shape[1] == 400 and picture.shape[0] == 600  # two 200-pixel views above the 400 map
    corner = picture[150:200, 150:200]  # below the label, inside the view: the view, scaled
    scaled = cv2.resize(view, (200, 200), interpolation=cv2.INTER_NEAREST)[150:200, 150:200]
    assert np.array_equal(corner, scaled)
    envs = vecenv.NavigationVectorEnv(num_envs=3, kitchens="FloorPlan1", render_mode="rgb_array")
    envs.reset(seed=0)
    assert envs.render().shape == (600, 400, 3) and envs.metadata["render_fps"] > 0
    assert vecenv.NavigationVectorEnv(num_envs=1, kitchens="FloorPlan1").render() is None


def test_vector_env_without_autoreset_waits_for_reset_mask(floorplan1_tasks):
    """gymnasium's DISABLED mode, as the trainer steps it: the ending step returns the episode's last
    observation and its final_info; the finished sub-envs refuse to step until reset by mask, and
    only they get new episodes; `reach` draws curriculum starts."""
    from gymnasium.vector import AutoresetMode

    envs = vecenv.NavigationVectorEnv(
        num_envs=4, kitchens="FloorPlan1", autoreset_mode="disabled", max_steps=3
    )
    assert envs.metadata["autoreset_mode"] == AutoresetMode.DISABLED
    envs.reset(seed=0)
    for _ in range(2):
        _, _, terminated, truncated, infos = envs.step(np.full(4, STOP - 1, np.int64))  # LookDown
        assert not infos["_final_info"].any()
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
        gymenv.NavigationGymEnv("FloorPlan21", targets="seen")
    with pytest.raises(vecenv.VecEnvError, match="num_envs"):
        vecenv.NavigationVectorEnv(num_envs=0, kitchens="FloorPlan1")
    envs = vecenv.NavigationVectorEnv(num_envs=2, kitchens="FloorPlan1")
    envs.reset(seed=0)
    with pytest.raises(vecenv.VecEnvError, match="2 integers"):
        envs.step(np.zeros(3, np.int64))
    with pytest.raises(vecenv.VecEnvError, match="0..9"):
        envs.step(np.array([0, 10]))


def test_every_kitchen_and_split_has_an_id_and_registering_loads_no_torch():
    from gymnasium.envs.registration import registry

    from kgnavbench.kitchens import KITCHEN_NAMES

    for name in (*KITCHEN_NAMES, *vecenv.SPLIT_NAMES):
        assert f"kgnavbench/{name}-v0" in registry
    # `import kgnavbench` (every command line start) registers them without importing torch
    code = "import sys, kgnavbench, kgnavbench.cli; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize(
    "keywords,named",
    [
        ({"views": "false"}, "views must be True or False, not 'false'"),
        ({"max_steps": 2**63}, "max_steps must be a whole number in 1..1,000,000"),
        ({"num_envs": 10**6}, "num_envs must be a whole number in 1..4,096"),
    ],
)
def test_the_vector_env_refuses_keywords_it_cannot_honour(keywords, named, floorplan1_tasks):
    with pytest.raises(vecenv.VecEnvError, match=named):
        vecenv.NavigationVectorEnv(**{"num_envs": 2, "kitchens": "FloorPlan1", **keywords})


@pytest.mark.parametrize("seed", [-1, "0", [1, 2], 1.5, True])
def test_both_faces_refuse_a_seed_that_is_not_a_whole_number_from_0(seed, floorplan1_tasks):
    for env in (gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=2), gym.make("kgnavbench/FloorPlan1-v0")):
        with pytest.raises(vecenv.VecEnvError, match="seed must be a whole number >= 0 or None"):
            env.reset(seed=seed)


def test_check_env_passes_with_a_curriculum_since_a_seed_starts_the_env_over(floorplan1_tasks):
    """A seeded reset starts the curriculum over: the same seed gives the same episodes however far
    the curriculum had moved (gymnasium's checker resets with one seed around its steps)."""
    env = gym.make("kgnavbench/FloorPlan1-v0", curriculum_steps=5)
    check_env(env.unwrapped, skip_render_check=True)
    first, _ = env.reset(seed=7)
    for _ in range(20):
        env.step(0)
    again, _ = env.reset(seed=7)
    assert all(np.array_equal(first[k], again[k]) for k in first)
    vector = gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=3, curriculum_steps=5)
    first, _ = vector.reset(seed=7)
    vector.step(np.zeros(3, np.int64))
    again, _ = vector.reset(seed=7)
    assert all(np.array_equal(first[k], again[k]) for k in first)


ASYNC = """
import gymnasium as gym, numpy as np, kgnavbench, torch
torch.ones(1 << 20).sum()  # the parent's torch has used its thread pool before the fork
envs = gym.make_vec("kgnavbench/FloorPlan1-v0", num_envs=2, vectorization_mode="async")
observations, infos = envs.reset(seed=0)
observations, rewards, *_ = envs.step(np.array([4, 5]))
envs.close()
print(observations["features"].shape, rewards.tolist())
"""


def test_gymnasiums_async_vector_env_runs_its_forked_workers(floorplan1_tasks, tmp_path):
    """gymnasium's AsyncVectorEnv forks workers that build the env with torch: one torch thread in a
    forked child (`encoder._one_torch_thread_after_fork`), or they wait forever on the parent's pool."""
    script = tmp_path / "async_env.py"
    script.write_text(ASYNC)
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "(2, 512) [-0.01, -0.01]"


def test_a_registered_ids_kitchens_cannot_be_replaced(floorplan1_tasks):
    with pytest.raises(vecenv.VecEnvError, match="kitchens='FloorPlan2' cannot replace them"):
        gym.make("kgnavbench/FloorPlan1-v0", kitchens="FloorPlan2")
    assert gym.make("kgnavbench/FloorPlan1-v0", kitchens="FloorPlan1").unwrapped.space.kitchens == [
        "FloorPlan1"
    ]


def test_a_reach_beyond_every_distance_draws_from_every_start(space, floorplan1_tasks):
    """reach is "at most that far": 2**21 or 10**30 is no bound (never an overflow, nor a key that
    spills into the next target's starts): each start is one of its own target's, at a distance
    that target has."""
    graph = floorplan1_tasks.graph
    startable = space.closed & (graph.pitch == 0)
    farthest = np.where(startable & (space.dist >= 0), space.dist, -1).max(1)
    for reach in (2**21, 10**30):
        nav = vecenv.Navigators(space, np.zeros(2000, np.int64))
        nav.draw(np.arange(2000), np.random.default_rng(4), 200, reach=reach)
        dist = space.dist[nav.target, nav.state]
        assert (dist >= 0).all() and startable[nav.state].all() and (dist <= farthest[nav.target]).all()
    env = gym.make("kgnavbench/FloorPlan1-v0")
    env.reset(seed=0, options={"reach": 10**30})
    with pytest.raises(vecenv.VecEnvError, match="max_steps must be a whole number in 1..1,000,000"):
        env.reset(options={"max_steps": 2**63})


@pytest.mark.parametrize("action", [True, 3.0, "3", 10])
def test_the_single_env_refuses_an_action_that_is_no_integer_0_to_9(action, floorplan1_tasks):
    env = gym.make("kgnavbench/FloorPlan1-v0")
    env.reset(seed=0)
    with pytest.raises(vecenv.VecEnvError, match="action must be an integer in 0..9"):
        env.step(action)
