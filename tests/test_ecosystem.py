"""kgnavbench as other RL libraries expect it: Stable-Baselines3 PPO on the registered Gymnasium env,
and on the PettingZoo env through SuperSuit (in-place autoreset, flat Box observations)."""

from __future__ import annotations

import numpy as np
import pytest
import supersuit as ss
import torch
from pettingzoo.test import parallel_api_test
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env

import kgnavbench  # noqa: F401 - registers the Gymnasium ids
from kgnavbench.env import EnvError, parallel_env
from kgnavbench.graph import STOP


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_sb3_ppo_trains_on_the_registered_env(floorplan1_tasks):
    """docs/environments.md's recipe: 2,048 steps of PPO over 4 copies of kgnavbench/FloorPlan1-v0."""
    envs = make_vec_env("kgnavbench/FloorPlan1-v0", n_envs=4, seed=0)
    model = PPO("MultiInputPolicy", envs, n_steps=512, batch_size=256, n_epochs=2, seed=0, device="cpu")
    model.learn(total_timesteps=2048)
    assert model.num_timesteps == 2048
    observations = envs.reset()
    actions, _ = model.predict(observations)
    assert actions.shape == (4,) and ((actions >= 0) & (actions < 10)).all()


def test_sb3_ppo_trains_on_the_pettingzoo_env_through_supersuit(floorplan1_tasks):
    env = parallel_env(kitchen="FloorPlan1", n_agents=4, observation="box", autoreset=True, max_steps=200)
    venv = ss.pettingzoo_env_to_vec_env_v1(env)
    venv = ss.concat_vec_envs_v1(venv, 2, num_cpus=0, base_class="stable_baselines3")
    assert venv.num_envs == 8 and venv.observation_space.shape == (2 * (512 + 125),)
    # (SuperSuit's ConcatVecEnv has no seed(), which PPO(seed=...) calls: seed torch instead)
    torch.manual_seed(0)
    model = PPO("MlpPolicy", venv, n_steps=256, batch_size=256, n_epochs=2, device="cpu")
    model.learn(total_timesteps=2048)
    assert model.num_timesteps == 2048


def test_supersuit_keeps_the_results_of_episodes_that_all_end_in_one_step(floorplan1_tasks):
    """When every navigator ends in the same step SuperSuit resets the whole env and merges the reset's
    infos into the ended episodes': with autoreset the reset's infos are empty, so the ended episodes'
    success and lengths survive. And the infos hold nothing privileged unless asked for."""
    import supersuit as ss

    env = parallel_env(kitchen="FloorPlan1", n_agents=3, observation="box", autoreset=True, max_steps=50)
    venv = ss.pettingzoo_env_to_vec_env_v1(env)
    venv.reset(seed=0)
    _, _, terminations, _, infos = venv.step(np.full(3, STOP))  # all three Stop at once: all end
    assert terminations.all()
    for info in infos:
        assert info["episode_length"] == 1 and info["success"] is False and info["path_length"] == 0
        assert "state" not in info and "expert_action" not in info
    _, infos = parallel_env(kitchen="FloorPlan1", n_agents=1).reset(seed=0)
    assert "state" not in infos["navigator_0"] and "expert_action" not in infos["navigator_0"]
    _, infos = parallel_env(kitchen="FloorPlan1", n_agents=1, privileged=True).reset(seed=0)
    assert {"state", "expert_action"} <= set(infos["navigator_0"])


def test_autoreset_keeps_every_navigator_and_starts_its_next_episode_in_place(floorplan1_tasks):
    env = parallel_env(kitchen="FloorPlan1", n_agents=6, autoreset=True, max_steps=30)
    observations, _ = env.reset(seed=2)
    rng = np.random.default_rng(0)
    ended = 0
    for _ in range(200):
        actions = {a: int(STOP if rng.random() < 0.1 else rng.integers(0, STOP)) for a in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)
        assert env.agents == env.possible_agents and set(observations) == set(env.possible_agents)
        for a in env.agents:
            if terminations[a] or truncations[a]:
                ended += 1
                assert 1 <= infos[a]["episode_length"] <= 30  # the ended episode's statistics
                # the new episode's first observation: the agent stands on a training start
                assert env._steps[env.possible_agents.index(a)] == 0
    assert ended > 20


# (not autoreset: PettingZoo's API has a finished agent leave, which autoreset is there to avoid)
@pytest.mark.filterwarnings("ignore::kgnavbench.env.UnknownOptionWarning")  # its {"options": 1}
@pytest.mark.parametrize("options", [{"observation": "box"}, {"features": True}])
def test_the_new_options_pass_pettingzoos_api_test(floorplan1_tasks, options):
    parallel_api_test(parallel_env(kitchen="FloorPlan1", n_agents=3, max_steps=40, **options), num_cycles=60)


def test_box_and_feature_observations_match_the_cache(floorplan1_tasks):
    from kgnavbench.encoder import encoder_feature_stats, standardize, state_features

    features = standardize(state_features("FloorPlan1"), encoder_feature_stats()).numpy()
    objects = np.asarray(floorplan1_tasks.graph.object_vectors)
    box = parallel_env(kitchen="FloorPlan1", n_agents=2, observation="box", privileged=True)
    both = parallel_env(kitchen="FloorPlan1", n_agents=2, features=True)
    b, infos = box.reset(seed=5)
    d, _ = both.reset(seed=5)
    for a in box.agents:
        s = infos[a]["state"]
        assert box.observation_space(a).contains(b[a]) and both.observation_space(a).contains(d[a])
        assert np.array_equal(b[a][:512], features[s]) and np.array_equal(b[a][512:637], objects[s])
        assert np.array_equal(d[a]["features"], features[s])
        assert np.array_equal(b[a][637:1149], d[a]["target_features"])
    with pytest.raises(EnvError, match="observation"):
        parallel_env(kitchen="FloorPlan1", observation="pixels")
