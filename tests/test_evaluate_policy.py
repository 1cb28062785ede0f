"""`kgnavbench.evaluate_policy`: your own policy on Table I's fixed episodes, without a plugin file,
as a callable on batched observations or as an object with Stable-Baselines3's predict."""

from __future__ import annotations

import numpy as np
import pytest

import kgnavbench
from kgnavbench.evaluate import EvalConfig, evaluate
from kgnavbench.graph import STOP
from kgnavbench.metrics import summary_as_json

TURNER = """
DESCRIPTION = "turns right, then stops on its fourth step"


class Policy:
    def reset(self, agent):
        self.steps = {}

    def act(self, observations, infos):
        return {a: 9 if self.steps.setdefault(a, []).append(0) or len(self.steps[a]) >= 4 else 4
                for a in observations}


def make_policy(config, spec):
    return Policy()
"""


def test_a_callable_gives_the_summary_eval_gives_a_plugin(tmp_path, monkeypatch, floorplan1_tasks):
    """The same actions through evaluate_policy and through a plugin file: the same summary."""
    steps = {"n": 0}

    def turner(observations):
        n = len(observations["features"])
        assert set(observations) >= {"features", "target_features", "view_objects", "target_objects"}
        assert observations["features"].shape == (n, 512)
        steps["n"] += 1
        return np.full(n, STOP if steps["n"] >= 4 else 4)

    got = kgnavbench.evaluate_policy(turner, kitchens=["FloorPlan1"], episodes=2)
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "turner.py").write_text(TURNER)
    monkeypatch.chdir(tmp_path)
    config = EvalConfig("turner", kitchens=("FloorPlan1",), episodes_per_target=2)
    want = evaluate(config, tmp_path / "runs", progress=lambda line: None).summary
    assert got["summary"] == summary_as_json(want)
    assert got["episodes"] == want[("all", "all")].episodes
    assert {m["episode_length"] for m in got["summary"].values() if m["episodes"]} == {4.0}


class Recurrent:
    """A predict() with an sb3-contrib-shaped state (layers, agents, units): each agent's state must
    come back to it, counting its steps; episode_start is True on its first step only."""

    def __init__(self):
        self.calls = 0

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        n = len(observation["features"])
        self.calls += 1
        if self.calls == 1:
            assert state is None and episode_start.all()
            state = (np.zeros((1, n, 3)), np.zeros((1, n, 3)))
        else:
            assert not episode_start.any() and state[0].shape == (1, n, 3)
            assert (state[0][0, :, 0] == self.calls - 1).all()  # every agent's own count came back
        counted = tuple(s + 1 for s in state)
        actions = np.where(counted[0][0, :, 0] >= 3, STOP, 4)
        return actions, counted


def test_an_sb3_style_predict_keeps_each_agents_recurrent_state(floorplan1_tasks):
    got = kgnavbench.evaluate_policy(Recurrent(), kitchens=["FloorPlan1"], episodes=1)
    assert {m["episode_length"] for m in got["summary"].values() if m["episodes"]} == {3.0}


def test_a_stable_baselines3_model_is_evaluated_in_one_call(floorplan1_tasks):
    gymnasium = pytest.importorskip("gymnasium")
    sb3 = pytest.importorskip("stable_baselines3")
    env = gymnasium.make("kgnavbench/FloorPlan1-v0")
    model = sb3.PPO("MultiInputPolicy", env, n_steps=16, batch_size=16, seed=0, device="cpu")
    got = kgnavbench.evaluate_policy(model, kitchens=["FloorPlan1"], episodes=1)
    assert got["episodes"] == got["summary"]["all/all"]["episodes"] > 0
    with pytest.raises(ValueError, match="callable on observations or an object with predict"):
        kgnavbench.evaluate_policy(object(), kitchens=["FloorPlan1"], episodes=1)


@pytest.mark.parametrize("example", ["sb3_ppo.py", "cleanrl_ppo.py"])
def test_the_examples_run_and_end_in_a_json_summary(example, hermetic_cache):
    """examples/: a few seconds each, so that they cannot rot; the last line is evaluate_policy's JSON."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    path = Path(__file__).parent.parent / "examples" / example
    out = subprocess.run(
        [sys.executable, str(path), "--steps", "4096", "--envs", "4", "--episodes", "1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["episodes"] == 7 and "seen_seen/static" in result["summary"]


@pytest.mark.parametrize(
    "keywords,named",
    [
        ({"kitchens": []}, "kitchens must be a non-empty list"),
        ({"kitchens": "FloorPlan1"}, "kitchens must be a non-empty list"),
        ({"seed": 1.5}, "seed must be a whole number, got 1.5"),
        ({"seed": True}, "seed must be a whole number"),
        ({"episodes": "2"}, "episodes must be a whole number, got '2'"),
        ({"progress": 3}, "progress must be callable"),
        ({"deterministic": "yes"}, "deterministic must be true or false"),
        ({"stop_noop": "yes"}, "stop_noop must be true or false"),
        ({"timeout": 0}, "timeout must be seconds"),
        ({"timeout": float("nan")}, "timeout must be seconds"),
        ({"timeout": "5"}, "timeout must be seconds"),
        ({"state_axis": -1}, "state_axis must be an axis"),
        ({"state_axis": 1.0}, "state_axis must be an axis"),
    ],
)
def test_evaluate_policy_refuses_arguments_the_cli_would(keywords, named):
    with pytest.raises(kgnavbench.EvalError, match=named):
        kgnavbench.evaluate_policy(lambda obs: np.zeros(len(obs["features"]), np.int64), **keywords)


@pytest.mark.parametrize(
    "actions,named",
    [
        (lambda n: np.full(n, 9.9), "actions of type float64"),  # never truncated into Stop
        (lambda n: np.full(n, 0.99, np.float32), "actions of type float32"),
        (lambda n: np.ones(n, bool), "actions of type bool"),
        (lambda n: np.full(n, 10), "action 10; actions are 0..9"),
        (lambda n: np.full(n + 1, 1), "actions for"),
    ],
)
def test_evaluate_policy_refuses_actions_that_are_not_integers_0_to_9(actions, named, floorplan1_tasks):
    with pytest.raises(kgnavbench.EvalError, match=named):
        kgnavbench.evaluate_policy(
            lambda obs: actions(len(obs["features"])), kitchens=["FloorPlan1"], episodes=1
        )


class RowsPerAgent:
    """A predict() whose recurrent state is one bare array of shape (agents, units), agents on axis 0,
    as wide as the first batch (FloorPlan1's 34 agents at episodes=1): column 0 counts steps, column 1
    is the agent's own episode length (2, 3 or 4), so agents finish at different steps and the batch
    shrinks. A state sliced on the wrong axis would give other agents' lengths."""

    def __init__(self, units: int | None = None):
        self.units = units

    def predict(self, observation, state=None, episode_start=None, deterministic=False):
        n = len(observation["features"])
        if state is None:
            self.units = self.units or n
            state = np.zeros((n, self.units), np.int64)
            state[:, 1] = np.arange(n) % 3 + 2
        assert isinstance(state, np.ndarray) and state.shape == (n, self.units)  # bare comes back bare
        assert len(set(state[:, 0])) == 1  # the agents still walking started together
        state = state.copy()
        state[:, 0] += 1
        return np.where(state[:, 0] >= state[:, 1], STOP, 4), state


def test_a_recurrent_state_is_kept_on_its_declared_agent_axis(floorplan1_tasks):
    got = kgnavbench.evaluate_policy(RowsPerAgent(), kitchens=["FloorPlan1"], episodes=1, state_axis=0)
    assert got["episodes"] == 34
    assert got["summary"]["all/all"]["episode_length"] == pytest.approx(np.mean(np.arange(34) % 3 + 2))
    with pytest.raises(kgnavbench.EvalError, match=r"shape \(34, 5\), not 34 agents on axis 1; pass"):
        kgnavbench.evaluate_policy(RowsPerAgent(units=5), kitchens=["FloorPlan1"], episodes=1)


def test_a_policy_call_past_the_timeout_ends_the_evaluation_with_where_it_waited(floorplan1_tasks):
    import signal
    import time

    def sleeper(observations):
        time.sleep(30)

    signal.setitimer(signal.ITIMER_REAL, 0)
    waited = r"did not return within 0.5 s \(FloorPlan1, step 1\)"
    with pytest.raises(kgnavbench.EvalError, match=waited):
        kgnavbench.evaluate_policy(sleeper, kitchens=["FloorPlan1"], episodes=1, timeout=0.5)
    from kgnavbench import plugins

    assert plugins.step_timeout is None  # the limit was the call's own


def test_the_arrival_rule_evaluates_with_stop_a_no_op_as_eval_does(tmp_path, monkeypatch, floorplan1_tasks):
    """success_rule="arrival" was always refused (its EvalConfig kept stop_ends): it implies a no-op
    Stop, as eval's --success-rule arrival does, and gives eval's summary for the same actions."""
    steps = {"n": 0}

    def turner(observations):  # three right turns, then Stop: a no-op, so every episode runs to its cap
        steps["n"] += 1
        return np.full(len(observations["features"]), STOP if steps["n"] >= 4 else 4)

    got = kgnavbench.evaluate_policy(turner, kitchens=["FloorPlan1"], episodes=1, success_rule="arrival")
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "turner.py").write_text(TURNER)
    monkeypatch.chdir(tmp_path)
    config = EvalConfig(
        "turner", success_rule="arrival", stop_ends=False, kitchens=("FloorPlan1",), episodes_per_target=1
    )
    want = evaluate(config, tmp_path / "runs", progress=lambda line: None).summary
    assert got["summary"] == summary_as_json(want)
    assert min(m["episode_length"] for m in got["summary"].values() if m["episodes"]) > 4
