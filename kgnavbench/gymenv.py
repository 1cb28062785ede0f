"""Stage 9 — gymenv: one navigator as a gymnasium.Env (`gym.make("kgnavbench/FloorPlan1-v0")`).

The single-env face of kgnavbench/vecenv.py's batched simulator: the same actions, observations,
rewards and termination (vecenv's module docstring states them), one navigator whose kitchen is drawn
per episode from `kitchens` (a kitchen, a split or a list). reset(options=...) can start a given
episode (GYM_RESET_OPTIONS).
"""

from __future__ import annotations

import numpy as np
from gymnasium import Env, spaces

from .env import MAX_EPISODE_STEPS, TRAINING_MAX_STEPS, _is_integer, checked_seed, whole_number_in
from .vecenv import RENDER_FPS, Navigation, VecEnvError, observation_space
from .world import ACTIONS

GYM_RESET_OPTIONS = ("target", "start", "max_steps", "reach")


class NavigationGymEnv(Navigation, Env):
    """One navigator in `kitchens` (a kitchen, a split or a list; the kitchen drawn per episode), as a
    gymnasium.Env (module docstring). reset(options={"target": id, "start": state}) starts a given
    episode instead (state: the kitchen's local state index, as in the task file's fixed episodes),
    with options["max_steps"] its cap; options["reach"]: a drawn start at most that far."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": RENDER_FPS}

    def __init__(
        self,
        kitchens="FloorPlan1",
        targets: str | None = None,
        success_rule: str = "destination",
        stop_ends: bool = True,
        max_steps: int = TRAINING_MAX_STEPS,
        views: bool = False,
        render_mode: str | None = None,
        curriculum_steps: int = 0,
        observation: str = "dict",
    ):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise VecEnvError(f"unknown render_mode {render_mode!r}; choose None or 'rgb_array'")
        self.render_mode = render_mode
        self._setup(1, kitchens, targets, success_rule, stop_ends, max_steps, views, observation)
        self._curriculum(curriculum_steps)
        self.observation_space = observation_space(views, observation=observation)
        self.action_space = spaces.Discrete(len(ACTIONS))
        self._rows = {
            (self.space.kitchens[k], t): r
            for r, (k, t) in enumerate(zip(self.space.target_kitchen.tolist(), self.space.target_ids))
        }
        self._reset_once = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """A new episode (options: GYM_RESET_OPTIONS). A seed starts the env over, its curriculum too:
        the same seed gives the same episodes (what gymnasium's check_env asks)."""
        if seed is not None:
            seed = checked_seed(seed, VecEnvError)
            self.curriculum_done = 0
        super().reset(seed=seed)
        if options is not None and not isinstance(options, dict):
            raise VecEnvError(f"options must be a dict, not {type(options).__name__}")
        options = dict(options or {})
        unknown = sorted(str(k) for k in options if k not in GYM_RESET_OPTIONS)
        if unknown:
            raise VecEnvError(f"unknown reset options {unknown}; known: {', '.join(GYM_RESET_OPTIONS)}")
        cap = self.max_steps
        if "max_steps" in options:
            cap = whole_number_in(options["max_steps"], "max_steps", 1, MAX_EPISODE_STEPS, VecEnvError)
        nav, sp = self.navigators, self.space
        if "target" in options:
            if "reach" in options:
                raise VecEnvError("reach draws a start; with target and start the episode is given")
            self._begin(options, cap)
        else:
            if "start" in options:
                raise VecEnvError("start needs its target: reset(options={'target': id, 'start': state})")
            reach = options.get("reach")
            if reach is not None and (not _is_integer(reach) or reach < 0):
                raise VecEnvError(f"reach must be a whole number of actions >= 0, not {reach!r}")
            nav.kitchen[0] = self.np_random.integers(len(sp.kitchens))
            nav.draw(
                np.zeros(1, np.int64), self.np_random, cap, self.reach() if reach is None else int(reach)
            )
        self._reset_once = True
        return self._single(self._gather()), self._info()

    def _begin(self, options: dict, cap: int) -> None:
        sp = self.space
        matches = [r for (k, t), r in self._rows.items() if t == options["target"]]
        if not matches:
            raise VecEnvError(f"{options['target']!r} is not a target of {', '.join(sp.kitchens)}")
        row = matches[0]
        k = int(sp.target_kitchen[row])
        local = options.get("start")
        n_local = int(sp.offsets[k + 1] - sp.offsets[k])
        if not _is_integer(local) or not 0 <= local < n_local:
            raise VecEnvError(
                f"start must be a state index of {sp.kitchens[k]} (0..{n_local - 1}), not {local!r}"
            )
        start = int(sp.offsets[k]) + int(local)
        if sp.dist[row, start] < 0:
            raise VecEnvError(f"the target {options['target']!r} cannot be reached from state {local}")
        self.navigators.kitchen[0] = k
        self.navigators.begin(np.zeros(1, np.int64), np.array([row]), np.array([start]), cap)

    def step(self, action):
        if isinstance(action, (bool, np.bool_)) or not self.action_space.contains(action):
            raise VecEnvError(f"action must be an integer in 0..{len(ACTIONS) - 1}, not {action!r}")
        if not self._reset_once:
            raise VecEnvError("step() before reset(): reset the env first")
        rewards, terminated, truncated = self.navigators.step(np.array([int(action)], np.int64))
        self.curriculum_done += 1
        info = self._info()
        if terminated[0] or truncated[0]:
            info.update({k: v[0].item() for k, v in self._episode_info(slice(0, 1)).items()})
        return self._single(self._gather()), float(rewards[0]), bool(terminated[0]), bool(truncated[0]), info

    def render(self):
        """rgb_array: the navigator's egocentric view and the target image above the top-down map of
        its kitchen, with the navigator and its target marked."""
        if self.render_mode is None:
            return None
        if not self._reset_once:
            raise VecEnvError("render() before reset()")
        return self._picture(0)

    def _single(self, batch):
        if self.observation == "box":
            return batch[0]
        return {key: value[0] for key, value in batch.items()}

    def _info(self) -> dict:
        nav = self.navigators
        return {
            "kitchen": self.space.kitchens[nav.kitchen[0]],
            "target": self.space.target_ids[nav.target[0]],
        }
