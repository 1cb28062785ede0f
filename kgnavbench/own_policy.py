"""Stage 24 — own_policy: your own policy on Table I's fixed episodes, without a plugin file.

`evaluate_policy(policy)` takes a callable on batched observations, or any object with
Stable-Baselines3's `predict` (a trained SB3 model, recurrent ones included), and runs it through the
evaluation protocol of kgnavbench/evaluate.py: the same fixed episodes, caps and rules as `kgnavbench
eval`, the same summary. Nothing is written to disk. `kgnavbench.evaluate_policy` loads it on first use.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import plugins
from .evaluate import (
    EPISODES_PER_TARGET,
    EvalConfig,
    EvalError,
    evaluate_kitchen,
    summarize,
    summary_as_json,
)
from .plugins import PluginError
from .world import ACTIONS

OBSERVATION_KEYS = ("features", "target_features", "view_objects", "target_objects")  # the vector env's


@dataclass
class _GivenPlugin:
    """What evaluate_kitchen needs of a plugin, for a policy handed over in Python."""

    policy: object
    deterministic: bool
    box: bool = False
    source: str = "evaluate_policy(policy)"
    privileged: bool = False

    state_axis: int = 1

    def make_policy(self, config, spec):
        return _BatchedPolicy(self.policy, self.deterministic, self.box, self.state_axis)


class _BatchedPolicy:
    """A callable on batched observations, or an object with Stable-Baselines3's predict, as a batched
    evaluation policy. The observations are a dict of arrays with a leading agent axis, keyed as the
    Gymnasium vector env's (`features`, `target_features`, `view_objects`, `target_objects`). For
    `predict`, `episode_start` is True on each agent's first step, and a recurrent state (an array or
    a tuple of arrays, SB3's) is kept per agent along its declared agent axis `state_axis` (1:
    sb3-contrib's (layers, agents, units) LSTM states) and handed back in the form it came in."""

    def __init__(self, policy, deterministic: bool, box: bool = False, state_axis: int = 1):
        self.policy, self.deterministic, self.box = policy, deterministic, box
        self.state_axis = state_axis
        self.bare = False  # the policy's state is one array, not a tuple
        self.predict = getattr(policy, "predict", None)
        if not callable(self.predict) and not callable(policy):
            raise EvalError("evaluate_policy needs a callable on observations or an object with predict()")
        self.state: dict[str, tuple] = {}  # agent -> its recurrent state (one row per array)
        self.fresh: set[str] = set()

    def reset(self, agent: str) -> None:
        self.fresh.add(agent)
        self.state.pop(agent, None)

    def act_batch(self, agents, observations, infos):
        if self.box:  # the Gymnasium envs' observation="box": BOX_PARTS side by side, float32
            from .vecenv import BOX_PARTS

            parts = [np.asarray(observations[k], np.float32) for k in BOX_PARTS]
            return self._actions(list(agents), np.concatenate(parts, axis=1))
        return self._actions(list(agents), {k: np.asarray(observations[k]) for k in OBSERVATION_KEYS})

    def _actions(self, agents: list[str], batch) -> np.ndarray:
        if not callable(self.predict):
            return checked_actions(self.policy(batch), len(agents))
        starts = np.array([a in self.fresh for a in agents])
        self.fresh.difference_update(agents)
        rows = [self.state.get(a) for a in agents]
        state = None
        if rows and all(r is not None for r in rows):  # every agent's state, stacked back on its axis
            axis = self.state_axis
            state = tuple(np.stack([r[i] for r in rows], axis=axis) for i in range(len(rows[0])))
            state = state[0] if self.bare else state
        answer = self.predict(batch, state=state, episode_start=starts, deterministic=self.deterministic)
        if not isinstance(answer, tuple) or len(answer) != 2:
            raise EvalError(
                f"the policy's predict() returned {type(answer).__name__}; it returns (actions, state), "
                "as Stable-Baselines3's does"
            )
        actions, state = answer
        if state is not None:
            self.bare = isinstance(state, np.ndarray)
            arrays = (state,) if self.bare else tuple(np.asarray(s) for s in state)
            for array in arrays:
                _check_state_axis(array, self.state_axis, len(agents))
            for j, agent in enumerate(agents):
                self.state[agent] = tuple(np.take(s, j, axis=self.state_axis) for s in arrays)
        return checked_actions(actions, len(agents))


def checked_actions(actions, n: int) -> np.ndarray:
    """A policy's actions as (n,) int64, or an EvalError naming what is wrong: they must be integers
    (an int, or an integer-typed array; floats and bools are never cast: 9.9 would become Stop and a
    probability 0.99 action 0) in 0..9, one per agent."""
    a = np.asarray(actions)
    if a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
        raise EvalError(
            f"the policy returned actions of type {a.dtype} ({ascii(a.reshape(-1)[:3].tolist())}...); "
            f"actions are integers 0..{len(ACTIONS) - 1}, one per agent"
        )
    if a.size != n:
        raise EvalError(f"the policy returned {a.size} actions for {n} agents (shape {a.shape})")
    a = a.reshape(n).astype(np.int64)
    bad = a[(a < 0) | (a >= len(ACTIONS))]
    if len(bad):
        raise EvalError(f"the policy returned action {int(bad[0])}; actions are 0..{len(ACTIONS) - 1}")
    return a


def _check_state_axis(array: np.ndarray, axis: int, n: int) -> None:
    """The recurrent state's agent axis is declared (evaluate_policy's state_axis), never guessed: an
    array without n rows on it is an error, since slicing another axis would mix agents' states."""
    if array.ndim <= axis or array.shape[axis] != n:
        raise EvalError(
            f"the policy's recurrent state has shape {array.shape}, not {n} agents on axis {axis}; "
            f"pass evaluate_policy(..., state_axis=N) with the axis that holds one row per agent"
        )


def evaluate_policy(
    policy,
    *,
    split: str = "table",
    kitchens=None,
    episodes: int = EPISODES_PER_TARGET,
    success_rule: str = "destination",
    stop_noop: bool = False,
    seed: int = 0,
    deterministic: bool = False,
    observation: str = "dict",
    targets: str = "all",
    progress=None,
    timeout: float | None = None,
    state_axis: int = 1,
) -> dict:
    """Table I's fixed episodes for your own policy, no plugin file: the same episodes, caps and rules
    as `kgnavbench eval`, and the same summary as `eval --json` ({"summary": {"column/kind": metrics}},
    an empty cell's NaN as None), with the number of episodes.

    `policy` is a callable on batched observations (a dict of arrays with a leading agent axis, keyed
    as the Gymnasium vector env's: features, target_features, view_objects, target_objects) returning
    one action per agent, or any object with Stable-Baselines3's `predict(observation, state=None,
    episode_start=None, deterministic=False)` (a trained SB3 model; a recurrent one's state is kept per
    agent through `episode_start`). observation="box": the policy gets the Gymnasium envs' flat Box
    instead, one float32 row of 1274 per agent (`vecenv.BOX_PARTS`), as a model trained on
    observation="box" expects. `success_rule`: "destination" (default, the paper's), "visible"
    (SAVN's) or "arrival" (Zhu et al.'s: arriving succeeds, by any action); `stop_noop`: a Stop that
    does not succeed is a no-op instead of ending the episode (eval's --stop-noop; "arrival" implies
    it). targets="seen": only the seen targets of training kitchens (Table I's
    seen/seen cells), "all" (default): every target. `timeout`: seconds one call of the policy may
    take before the evaluation ends with an EvalError naming the kitchen and step (as eval's
    --step-timeout; a policy that defeats it ends the process with that line); None (default): no
    limit, and a line on stderr every minute naming where it waits. `state_axis`: the agent axis of
    a recurrent state's arrays (1: sb3-contrib's (layers, agents, units)). Nothing is written to disk;
    results are not cached."""
    if observation not in ("dict", "box"):
        raise EvalError(f"unknown observation {observation!r}; choose 'dict' or 'box'")
    for name, value in (("episodes", episodes), ("seed", seed)):
        if not isinstance(value, int) or isinstance(value, bool):
            raise EvalError(f"evaluate_policy's {name} must be a whole number, got {ascii(value)}")
    if kitchens is not None and not isinstance(kitchens, (str, bytes)) and hasattr(kitchens, "__iter__"):
        kitchens = list(kitchens)
    if kitchens is not None and (not isinstance(kitchens, list) or not kitchens):
        raise EvalError(
            f"evaluate_policy's kitchens must be a non-empty list of kitchen names, got {ascii(kitchens)} "
            "(None: every kitchen of the split)"
        )
    if progress is not None and not callable(progress):
        raise EvalError(f"evaluate_policy's progress must be callable (print, say), got {ascii(progress)}")
    if not isinstance(deterministic, bool):
        raise EvalError(f"evaluate_policy's deterministic must be true or false, got {ascii(deterministic)}")
    if not isinstance(stop_noop, bool):
        raise EvalError(f"evaluate_policy's stop_noop must be true or false, got {ascii(stop_noop)}")
    if targets not in ("all", "seen"):
        raise EvalError(f"unknown targets {targets!r}; choose 'all' or 'seen'")
    if timeout is not None and (
        isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not 0 < timeout < 1e6
    ):
        raise EvalError(
            f"evaluate_policy's timeout must be seconds in (0, 1e6) or None, got {ascii(timeout)}"
        )
    if isinstance(state_axis, bool) or not isinstance(state_axis, int) or not 0 <= state_axis <= 8:
        raise EvalError(f"evaluate_policy's state_axis must be an axis 0..8, got {ascii(state_axis)}")
    config = EvalConfig(
        method="evaluate_policy",
        success_rule=success_rule,
        stop_ends=not stop_noop and success_rule != "arrival",  # as eval's: arrival makes Stop a no-op
        split=split,
        kitchens=tuple(kitchens or ()),
        episodes_per_target=episodes,
        seed=seed,
    )
    plugin = _GivenPlugin(policy, deterministic, observation == "box", state_axis=state_axis)
    results = []
    limit_before, plugins.step_timeout = plugins.step_timeout, timeout
    try:
        for kitchen in config.kitchen_list():
            t0 = time.perf_counter()
            try:
                done = evaluate_kitchen(plugin, None, config, kitchen, seen_only=targets == "seen")
            except PluginError as e:  # the caller's policy, not a plugin file: the package's EvalError
                raise EvalError(str(e)) from e
            results += done
            if progress:
                progress(f"{kitchen}: {len(done)} episodes in {time.perf_counter() - t0:.1f} s")
    finally:
        plugins.step_timeout = limit_before
    return {"summary": summary_as_json(summarize(results)), "episodes": len(results)}
