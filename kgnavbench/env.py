"""Stage 7 — env: target-driven navigation in one kitchen as a PettingZoo ParallelEnv.

    env = kgnavbench.env.parallel_env(kitchen="FloorPlan1", n_agents=4)
    observations, infos = env.reset(seed=0)
    while env.agents:
        actions = {agent: env.action_space(agent).sample() for agent in env.agents}
        observations, rewards, terminations, truncations, infos = env.step(actions)

Several navigators share one kitchen. Each has its own target and its own episode; they neither see
nor block each other (each has its own receptacle state, too). An agent leaves `env.agents` when its
episode ends, as PettingZoo's parallel API requires; the environment is done when all have.

Actions: Discrete(10), the paper's order — 0 MoveAhead, 1 MoveBack, 2 MoveRight, 3 MoveLeft (0.25 m),
    4 RotateRight, 5 RotateLeft (90°), 6 LookUp, 7 LookDown (30°), 8 OpenObject, 9 Stop.
    A move into an obstacle fails and counts as a collision. OpenObject opens the visible openable
    receptacle nearest the image centre; any action but Stop closes it again.
Observations (per agent, a dict):
    "view"           uint8 (V, V, 3)  the current egocentric view (RGB)
    "target"         uint8 (V, V, 3)  the target image: the view at the target's destination
    "view_objects"   uint8 (125,)     1 for each object type visible in the current view
    "target_objects" uint8 (125,)     the same for the target image
    (V = 84 by default; types in `kgnavbench.kitchens.object_types()` order.) Views are looked up in
    the state graph's cache, so a step renders nothing. Arrays are read-only views of that cache.
    features=True adds "features" and "target_features", float32 (512,): the frozen encoder's
    features of the two views, standardized as the learned agents see them (kgnavbench/encoder.py).
    observation="box": instead of the dict, one fresh float32 (1274,) vector per agent: the view's
    features and visible types, then the target's (for libraries that want a Box, e.g. SuperSuit).
Rewards: -0.01 every step; +0.01 the first time the agent reaches a goal state; +10 on success.
Termination: Stop ends the episode (stop_ends=False: a Stop that does not succeed is a no-op).
    Success (the paper's, default success_rule="destination") = Stop at the target's destination, the
    state its image shows; success_rule="visible" (SAVN's) = Stop in any state where the target is
    visible, receptacle open or not; success_rule="arrival" (Zhu et al. 2017's) = arriving at the
    destination, by any action, ends the episode in success, and Stop is a no-op (stop_ends=False).
    Goal states (for the +0.01) follow the rule in force (`tasks.outcome` decides success).
    Truncation at max_steps (5000 in training; per episode in evaluation).
Infos (per agent, every step): success, path_length (actions, Stop not counted), episode_length,
    shortest_path (from the start, under the success rule), collisions, target, target_kind,
    target_seen, last_view_shows_target, kitchen; and, with privileged=True only (opt-in: a training
    loop must not learn from them by accident; in evaluation only a plugin with PRIVILEGED = True
    gets them: the oracle), state (the state graph's index) and expert_action (the BFS-optimal next
    action).

autoreset=True (outside PettingZoo's contract, for SuperSuit's vector envs): a navigator whose episode
    ends stays in `env.agents` and starts its next training episode in the same step; that step's
    observation is the new episode's first, its terminations/truncations and infos the ended one's.
    reset() then returns empty infos (SuperSuit merges a whole-env reset's infos into the ended
    episodes' when every navigator ended in one step).

Episodes: in training, reset draws each agent a target (`targets`: "seen", "unseen", "all" or a list
of object ids) and a start at pitch 0 at least 10 actions from the target's destination, from the
env's seeded generator.
Evaluation passes fixed episodes: reset(options={"episodes": [{"target": id, "start": state,
"max_steps": n}, ...]}), one per agent (fewer episodes than agents: the rest sit out).
"""

from __future__ import annotations

import difflib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from pettingzoo import ParallelEnv

from .errors import KgnavbenchError
from .graph import MOVES, OPEN, STOP, VIEW_SIZE, TaskError, expert_actions, goal_mask
from .kitchens import object_types
from .render import top_down_map
from .tasks import SUCCESS_RULES, KitchenTasks, load_tasks, outcome
from .world import ACTIONS

STEP_REWARD = -0.01
ARRIVAL_REWARD = 0.01
SUCCESS_REWARD = 10.0
TRAINING_MAX_STEPS = 5000
TARGET_SETS = ("seen", "unseen", "all")
# upper bounds that name the limit rather than fill the memory: the protocol's largest kitchen has
# fewer than 6,000 fixed episodes (one agent each), and no episode of it is longer than 5000 actions
MAX_AGENTS = 100_000
MAX_EPISODE_STEPS = 1_000_000
MIN_VIEW_SIZE, MAX_VIEW_SIZE = 8, 256  # every state's view is kept: 256 px is 400 MB for 2,000 states
OBSERVATION_FORMATS = ("dict", "box")
IS_MOVE = np.isin(np.arange(len(ACTIONS)), MOVES)  # per action: a move (a failed one is a collision)


RESET_OPTIONS = ("episodes",)  # reset(options=...): the fixed episodes, one per agent


class UnknownOptionWarning(UserWarning):
    """reset(options=...) with a key the env does not know (and that is no near miss of one)."""


class EnvError(KgnavbenchError, ValueError):
    """Bad environment input: unknown option, target, success rule or episode."""


def reward(first_arrival: np.ndarray, success: np.ndarray) -> np.ndarray:
    """The task's reward: -0.01 per step, +0.01 on the first arrival at a goal state, +10 on success."""
    return STEP_REWARD + ARRIVAL_REWARD * first_arrival + SUCCESS_REWARD * success


class Transition(NamedTuple):
    """What one action does to a batch of agents (arrays, one entry per agent)."""

    next_state: np.ndarray
    stop: np.ndarray  # the action was Stop
    collided: np.ndarray  # a move that failed
    on_goal: np.ndarray  # the next state is a goal state of the agent's target
    first_arrival: np.ndarray  # ... and the episode had not been on one before
    success: np.ndarray  # Stop on a goal state
    reward: np.ndarray
    terminated: np.ndarray  # success, or (stop_ends) any Stop
    truncated: np.ndarray  # not terminated, and the cap reached


def transition(
    next_state, ok, goal, state, action, row, arrived, steps, cap, stop_ends: bool, success_rule="destination"
) -> Transition:
    """The state-graph step: the one transition the PettingZoo env and the trainer's navigators both
    take. `next_state`, `ok` (S, 10): the graph's tables; `goal` (targets, S): goal states per target
    row; per agent its `state`, `action`, target `row`, whether it `arrived` at a goal state before,
    the actions it took before this one (`steps`) and its `cap`; `goal` follows `success_rule`, which
    decides success and the episode's end (`tasks.outcome`). Moves, OpenObject (with the auto-close of
    the graph), Stop, rewards and termination all come from here; the callers only keep counts."""
    nxt = next_state[state, action]
    stop = action == STOP
    on_goal = goal[row, nxt]
    success, terminated = outcome(success_rule, stop, on_goal, stop_ends)
    first_arrival = on_goal & ~arrived
    return Transition(
        next_state=nxt,
        stop=stop,
        collided=IS_MOVE[action] & ~ok[state, action],
        on_goal=on_goal,
        first_arrival=first_arrival,
        success=success,
        reward=reward(first_arrival, success),
        terminated=terminated,
        truncated=~terminated & (steps + 1 >= cap),
    )


def parallel_env(**kwargs) -> NavigationEnv:
    """PettingZoo's conventional constructor. Keyword arguments: see NavigationEnv."""
    return NavigationEnv(**kwargs)


@dataclass
class _TargetTables:
    """Per target of the env, arrays over states: goal or not, BFS distance, expert action."""

    goal: np.ndarray  # (T, S) bool
    dist: np.ndarray  # (T, S) int
    expert: np.ndarray  # (T, S) int
    visible: np.ndarray  # (T, S) bool, target visible (for last_view_shows_target)


class BatchObservations(Mapping):
    """The observations of many agents as arrays with a leading agent axis (`observation_arrays`): the
    per-agent dicts' keys, each gathered once, when first read."""

    def __init__(self, env: NavigationEnv, idx: np.ndarray):
        self._env, self._idx, self._arrays = env, idx, {}
        self._keys = ("view", "target", "view_objects", "target_objects")
        if env.features:
            self._keys += ("features", "target_features")

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._arrays:
            if key not in self._keys:
                raise KeyError(key)
            self._arrays[key] = self._env._observation_array(key, self._idx)
        return self._arrays[key]

    def __iter__(self):
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)


def whole_number_in(value, name: str, least: int, most: int, error: type[Exception]) -> int:
    """`value` as an int if it is a whole number (not a bool or a float) in least..most, else `error`
    naming it: the constructors' bound check, in the env and the vector env."""
    if not _is_integer(value) or not least <= value <= most:
        raise error(f"{name} must be a whole number in {least:,}..{most:,}, not {value!r}")
    return int(value)


def checked_seed(seed, error: type[Exception]) -> int:
    """A reset's seed: a whole number >= 0 (numpy's and Gymnasium's rule), else `error` naming it."""
    if not _is_integer(seed) or seed < 0:
        raise error(f"seed must be a whole number >= 0 or None, not {seed!r}")
    return int(seed)


def _is_integer(value) -> bool:
    """An int or a NumPy integer (also 0-d arrays of one, as gymnasium's Discrete.sample gives); not a
    bool, not a float."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


class NavigationEnv(ParallelEnv):
    metadata = {"name": "kgnavbench_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(
        self,
        kitchen: str = "FloorPlan1",
        n_agents: int = 4,
        targets: str | list[str] = "seen",
        success_rule: str = "destination",
        stop_ends: bool = True,
        max_steps: int = TRAINING_MAX_STEPS,
        view_size: int = VIEW_SIZE,
        render_mode: str | None = None,
        tasks: KitchenTasks | None = None,
        features: bool = False,
        observation: str = "dict",
        autoreset: bool = False,
        privileged: bool = False,
    ):
        if observation not in OBSERVATION_FORMATS:
            raise EnvError(f"unknown observation {observation!r}; choose one of {OBSERVATION_FORMATS}")
        flags = (("stop_ends", stop_ends), ("features", features), ("autoreset", autoreset))
        for name, value in (*flags, ("privileged", privileged)):
            if not isinstance(value, (bool, np.bool_)):  # "no" and "false" are true strings
                raise EnvError(f"{name} must be True or False, not {value!r}")
        if tasks is not None and not isinstance(tasks, KitchenTasks):
            raise EnvError(
                f"tasks must be a KitchenTasks (kgnavbench.tasks.load_tasks), not {type(tasks).__name__}"
            )
        if success_rule not in SUCCESS_RULES:
            raise EnvError(f"unknown success_rule {success_rule!r}; choose one of {SUCCESS_RULES}")
        if success_rule == "arrival" and stop_ends:
            raise EnvError("success_rule='arrival' makes Stop a no-op: pass stop_ends=False")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise EnvError(f"unknown render_mode {render_mode!r}; choose None or 'rgb_array'")
        n_agents = whole_number_in(n_agents, "n_agents", 1, MAX_AGENTS, EnvError)
        if not _is_integer(view_size) or not MIN_VIEW_SIZE <= view_size <= MAX_VIEW_SIZE:
            sizes = f"{MIN_VIEW_SIZE}..{MAX_VIEW_SIZE}"
            raise EnvError(f"view_size must be a whole number of pixels in {sizes}, not {view_size!r}")
        max_steps = whole_number_in(max_steps, "max_steps", 1, MAX_EPISODE_STEPS, EnvError)
        self.tasks = tasks if tasks is not None else load_tasks(kitchen, view_size)
        self.kitchen = self.tasks.kitchen
        self.graph = self.tasks.graph
        self.success_rule, self.stop_ends, self.max_steps = success_rule, stop_ends, max_steps
        self.render_mode = render_mode
        self.possible_agents = [f"navigator_{i}" for i in range(n_agents)]
        self.agents: list[str] = []
        self.training_targets = self._select_targets(targets)
        self._tables = self._target_tables()
        self._target_row = {t.object_id: k for k, t in enumerate(self.tasks.targets)}
        # what a step hands out, per state and per target row, kept ready for the per-agent dicts:
        # plain ndarray views of the (memory-mapped, read-only) cache, since indexing a np.memmap runs
        # Python code for every array it returns; and each target's destination, id, kind and seen
        self._views = np.asarray(self.graph.views)
        self._object_vectors = np.asarray(self.graph.object_vectors)
        self._destination = np.array([t.destination for t in self.tasks.targets], np.int64)
        self._target_meta = [(t.object_id, t.kind, t.seen) for t in self.tasks.targets]
        self._target_columns = {  # the same per target row, for the infos as arrays
            "target": np.array([t.object_id for t in self.tasks.targets], dtype=object),
            "target_kind": np.array([t.kind for t in self.tasks.targets], dtype=object),
            "target_seen": np.array([t.seen for t in self.tasks.targets], bool),
        }
        v = self.graph.views.shape[1]
        n_types = len(object_types())
        self.features, self.observation, self.autoreset = features, observation, autoreset
        if not isinstance(privileged, (bool, np.bool_)):
            raise EnvError(f"privileged must be True or False, not {privileged!r}")
        self.privileged = bool(privileged)  # infos with the state index and the expert action
        parts = {
            "view": spaces.Box(0, 255, (v, v, 3), np.uint8),
            "target": spaces.Box(0, 255, (v, v, 3), np.uint8),
            "view_objects": spaces.Box(0, 1, (n_types,), np.uint8),
            "target_objects": spaces.Box(0, 1, (n_types,), np.uint8),
        }
        if features or observation == "box":
            # the encoder's standardized per-state features, as the learned agents see them (torch
            # loads only for an env that hands out features)
            from .encoder import FEATURE_DIM, encoder_feature_stats, standardize, state_features

            stats = encoder_feature_stats()
            self._features = standardize(state_features(self.kitchen), stats).numpy()
            # observations hand out rows of this table: read-only, so that one agent's in-place
            # change cannot become another agent's observation
            self._features.flags.writeable = False
            # standardized ReLU features have no bounds of their own: -inf .. inf (readable, too)
            low, high = np.full(FEATURE_DIM, -np.inf, np.float32), np.full(FEATURE_DIM, np.inf, np.float32)
            parts["features"] = spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32)
            parts["target_features"] = spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32)
        if observation == "box":
            # one float32 row per state: its features then its visible types; an observation is the
            # view's row then the target's
            self._box_rows = np.concatenate([self._features, self._object_vectors.astype(np.float32)], 1)
            zeros, ones = np.zeros(n_types, np.float32), np.ones(n_types, np.float32)
            half_low, half_high = np.concatenate([low, zeros]), np.concatenate([high, ones])
            self._observation_space = spaces.Box(
                np.concatenate([half_low, half_low]), np.concatenate([half_high, half_high]), dtype=np.float32
            )
        else:
            self._observation_space = spaces.Dict(parts)
        self._action_spaces = {a: spaces.Discrete(len(ACTIONS)) for a in self.possible_agents}
        self._observation_spaces = {a: self._observation_space for a in self.possible_agents}
        self.np_random, _ = seeding.np_random(None)

    # -- spaces (PettingZoo wants the same object on every call: a dict lookup, no cache) -----------
    def observation_space(self, agent: str) -> spaces.Space:
        return self._observation_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self._action_spaces[agent]

    # -- set-up ----------------------------------------------------------------------------------
    def _select_targets(self, targets) -> list[int]:
        all_targets = self.tasks.targets
        if isinstance(targets, str):
            if targets not in TARGET_SETS:
                raise EnvError(f"unknown target set {targets!r}; choose {TARGET_SETS} or a list of ids")
            chosen = [
                k for k, t in enumerate(all_targets) if targets == "all" or t.seen == (targets == "seen")
            ]
        else:
            ids = {t.object_id: k for k, t in enumerate(all_targets)}
            unknown = [o for o in targets if o not in ids]
            if unknown:
                raise EnvError(f"{unknown} are not targets of {self.kitchen}")
            chosen = [ids[o] for o in targets]
        if not chosen:
            hint = ""
            if targets == "seen" and self.tasks.split != "train":
                hint = f": it is a {self.tasks.split} kitchen, all its targets are unseen; use targets='all'"
            raise EnvError(f"{self.kitchen} has no {targets} targets{hint}")
        return chosen

    def _target_tables(self) -> _TargetTables:
        n = self.graph.n_states
        goal, dist, expert, visible = [], [], [], []
        for t in self.tasks.targets:
            g = np.zeros(n, bool)
            g[list(t.goal_states)] = True
            visible.append(g)
            goal.append(goal_mask(n, t.goals(self.success_rule)))
            d = self.tasks.distances(t, self.success_rule)
            dist.append(d)
            expert.append(expert_actions(self.graph.next_state, d))
        return _TargetTables(np.array(goal), np.array(dist), np.array(expert), np.array(visible))

    def _draw_episode(self) -> tuple[int, int, int]:
        """(target row, start state, max steps) for training: a seeded target and a start at pitch 0
        at least MIN_START_DISTANCE actions from its destination, as in the fixed episodes."""
        row = self.training_targets[self.np_random.integers(len(self.training_targets))]
        far = self.tasks.training_starts(self.tasks.targets[row])
        return row, int(far[self.np_random.integers(len(far))]), self.max_steps

    def _parse_episode(self, episode) -> tuple[int, int, int]:
        try:
            row = self._target_row[episode["target"]]
            start, max_steps = episode["start"], episode.get("max_steps", self.max_steps)
        except KeyError as e:
            raise EnvError(f"bad episode {episode!r}: unknown target or missing key {e}") from e
        except (TypeError, AttributeError) as e:
            raise EnvError(f"bad episode {episode!r}: {e}") from e
        if not all(_is_integer(v) for v in (start, max_steps)):
            raise EnvError(f"bad episode {episode!r}: start and max_steps must be integers")
        start, max_steps = int(start), int(max_steps)
        if not 0 <= start < self.graph.n_states or not 1 <= max_steps <= MAX_EPISODE_STEPS:
            raise EnvError(f"bad episode {episode!r}: start or max_steps out of range")
        if self._tables.dist[row, start] < 0:
            raise EnvError(f"bad episode {episode!r}: the goal cannot be reached from the start")
        return row, start, max_steps

    # -- the episode -----------------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.np_random, _ = seeding.np_random(checked_seed(seed, EnvError))
        if options is not None and not isinstance(options, Mapping):
            raise EnvError(f"options must be a dict, not {type(options).__name__}")
        unknown = sorted(str(k) for k in (options or {}) if k != "episodes")
        # A typo ("episode") must not silently give random episodes: a near miss of a known option is
        # an error; any other key is a warning, not an error, because PettingZoo's own API test
        # resets with an arbitrary option ({"options": 1}) and expects it to be taken
        typos = [k for k in unknown if difflib.get_close_matches(k.lower(), RESET_OPTIONS, cutoff=0.6)]
        if typos:
            raise EnvError(f"unknown reset options {typos}; known: {', '.join(RESET_OPTIONS)}")
        if unknown:
            warnings.warn(
                f"kgnavbench: reset ignores unknown options {unknown}; known: {', '.join(RESET_OPTIONS)}",
                UnknownOptionWarning,
                stacklevel=2,
            )
        episodes = (options or {}).get("episodes")
        if episodes is not None:
            if not isinstance(episodes, (list, tuple)):
                raise EnvError(
                    f"options['episodes'] must be a list of episodes ({{'target': id, 'start': state}}, "
                    f"one per agent), not {type(episodes).__name__}"
                )
            if len(episodes) > len(self.possible_agents):
                raise EnvError(f"{len(episodes)} episodes for {len(self.possible_agents)} agents")
            drawn = [self._parse_episode(e) for e in episodes]
        else:
            drawn = [self._draw_episode() for _ in self.possible_agents]
        self.agents = self.possible_agents[: len(drawn)]
        n = len(drawn)
        self._row = np.array([d[0] for d in drawn], np.int64)
        self._state = np.array([d[1] for d in drawn], np.int64)
        self._start = self._state.copy()
        self._cap = np.array([d[2] for d in drawn], np.int64)
        self._steps = np.zeros(n, np.int64)
        self._path = np.zeros(n, np.int64)
        self._collisions = np.zeros(n, np.int64)
        self._success = np.zeros(n, bool)
        self._arrived = self._tables.goal[self._row, self._state]
        self._shortest = self._tables.dist[self._row, self._start]
        self._live = list(range(n))
        self._live_agents = list(self.agents)  # the names of _live, apart from the public env.agents
        self._trail = [int(self._state[0])] if n else []  # agent 0's states, for render()
        idx = np.arange(n)
        if self.autoreset:
            # no results yet, so no infos: SuperSuit resets the whole env when every navigator ended in
            # the same step and merges the reset's infos into the ended episodes' (their success and
            # lengths would read False and 0); the new episodes' infos come with their first step
            return self._observations(self._live_agents, idx), {a: {} for a in self._live_agents}
        return self._observations(self._live_agents, idx), self._infos(self._live_agents, idx)

    def _check_reset(self, what: str) -> None:
        if not hasattr(self, "_live"):
            raise EnvError(f"{what} before reset(): reset the env first")

    def step(self, actions: dict):
        self._check_reset("step()")
        live, names = self._live, self._live_agents
        try:
            given = [actions[a] for a in names]
        except KeyError as e:
            raise EnvError(f"no action for live agent {e}") from e
        # plain ints (the usual case) pass at C speed; anything else is checked one by one
        if not set(map(type, given)) <= {int} and not all(_is_integer(a) for a in given):
            raise EnvError(f"actions must be integers 0..{len(ACTIONS) - 1}, got {given}")
        act = np.array(given, np.int64).reshape(len(live))
        idx, t = self._advance(act)
        observations = self._observations(names, idx)
        rewards = dict(zip(names, t.reward.tolist()))
        terminations = dict(zip(names, t.terminated.tolist()))
        truncations = dict(zip(names, t.truncated.tolist()))
        infos = self._infos(names, idx)
        going = ~(t.terminated | t.truncated)
        if not going.all() and self.autoreset:
            # each finished navigator starts its next training episode where it is listed: its
            # observation is the new episode's first, its infos are still the ended episode's
            ended = idx[~going]
            for i in ended.tolist():
                self._begin(i, *self._draw_episode())
            observations.update(self._observations([names[j] for j in np.flatnonzero(~going)], ended))
        elif not going.all():
            self._leave(idx, names, going)
        self.agents = list(self._live_agents)
        return observations, rewards, terminations, truncations, infos

    # -- the batched face (evaluation of a policy with act_batch: arrays, no per-agent dicts) --------
    def observation_arrays(self) -> BatchObservations:
        """The live agents' observations (env.agents order) as arrays with a leading agent axis, each
        gathered when first read (a policy that reads only the features never copies a view)."""
        self._check_reset("observation_arrays()")
        return BatchObservations(self, np.array(self._live, np.int64))

    def info_arrays(self, privileged: bool = False) -> dict:
        """The live agents' infos as arrays (env.agents order); `state` and `expert_action` only when
        privileged."""
        self._check_reset("info_arrays()")
        return self._info_arrays(np.array(self._live, np.int64), privileged)

    def step_arrays(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
        """step() for arrays: one action per live agent in env.agents order -> rewards, terminated,
        truncated and the infos as arrays over the same agents (privileged ones included: the caller
        decides what a plugin sees); finished agents leave env.agents as in step(). Not with autoreset."""
        if self.autoreset:
            raise EnvError("step_arrays is for evaluation: not with autoreset=True")
        self._check_reset("step_arrays()")
        act = np.asarray(actions)
        if act.shape != (len(self._live),) or not np.issubdtype(act.dtype, np.integer):
            raise EnvError(f"actions must be {len(self._live)} integers, got {act.dtype} {act.shape}")
        names = self._live_agents
        idx, t = self._advance(act.astype(np.int64))
        infos = self._info_arrays(idx, privileged=True)
        going = ~(t.terminated | t.truncated)
        if not going.all():
            self._leave(idx, names, going)
        self.agents = list(self._live_agents)
        return t.reward, t.terminated, t.truncated, infos

    def _advance(self, act: np.ndarray) -> tuple[np.ndarray, Transition]:
        """The live agents (rows idx) take their actions: the transition and every counter it moves."""
        if ((act < 0) | (act >= len(ACTIONS))).any():
            raise EnvError(f"actions must be integers 0..{len(ACTIONS) - 1}, got {act.tolist()}")
        live = self._live
        idx = np.array(live, np.int64)
        t = transition(
            self.graph.next_state,
            self.graph.ok,
            self._tables.goal,
            self._state[idx],
            act,
            self._row[idx],
            self._arrived[idx],
            self._steps[idx],
            self._cap[idx],
            self.stop_ends,
            self.success_rule,
        )
        # a Stop that fails: the episode ends, or (stop_ends=False) nothing happens at all
        nxt = t.next_state
        self._state[idx] = nxt
        self._steps[idx] += 1
        self._path[idx] += ~t.stop
        self._collisions[idx] += t.collided
        self._arrived[idx] |= t.on_goal
        self._success[idx] = t.success

        if live and live[0] == 0:
            self._trail.append(int(nxt[0]))
        return idx, t

    def _leave(self, idx: np.ndarray, names: list[str], going: np.ndarray) -> None:
        """The agents whose episodes ended leave the live set."""
        self._live = idx[going].tolist()
        self._live_agents = [a for a, on in zip(names, going.tolist()) if on]

    def _begin(self, i: int, row: int, start: int, cap: int) -> None:
        """Agent row i starts a new episode (autoreset)."""
        self._row[i], self._state[i], self._start[i], self._cap[i] = row, start, start, cap
        self._steps[i] = self._path[i] = self._collisions[i] = 0
        self._success[i] = False
        self._arrived[i] = self._tables.goal[row, start]
        self._shortest[i] = self._tables.dist[row, start]

    def _observations(self, names: list[str], idx: np.ndarray) -> dict:
        """The observations of agents `names` (rows `idx`): dicts of read-only views of the cache,
        with `features` their rows of the standardized features too, or (observation="box") one
        fresh float32 vector each."""
        states, goals = self._state[idx].tolist(), self._destination[self._row[idx]].tolist()
        if self.observation == "box":
            rows = self._box_rows
            return {a: np.concatenate([rows[s], rows[d]]) for a, s, d in zip(names, states, goals)}
        views, vectors = self._views, self._object_vectors
        out = {
            a: {
                "view": views[s],
                "target": views[d],
                "view_objects": vectors[s],
                "target_objects": vectors[d],
            }
            for a, s, d in zip(names, states, goals)
        }
        if self.features:
            f = self._features
            for o, s, d in zip(out.values(), states, goals):
                o["features"], o["target_features"] = f[s], f[d]
        return out

    def _observation_array(self, key: str, idx: np.ndarray) -> np.ndarray:
        """One observation key of agents idx, stacked (a fresh array)."""
        if self.observation == "box":
            raise EnvError("observation arrays are the dict observation's keys, not observation='box'")
        if key in ("features", "target_features") and not self.features:
            raise KeyError(key)
        target = key in ("target", "target_objects", "target_features")
        states = self._destination[self._row[idx]] if target else self._state[idx]
        table = {"view": self._views, "target": self._views, "view_objects": self._object_vectors}
        table.update(target_objects=self._object_vectors)
        if self.features:
            table.update(features=self._features, target_features=self._features)
        return table[key][states]

    def _info_arrays(self, idx: np.ndarray, privileged: bool) -> dict:
        """The infos of agents idx as arrays (the per-agent dicts' keys; privileged ones on request)."""
        row, state = self._row[idx], self._state[idx]
        out = {
            "success": self._success[idx],
            "path_length": self._path[idx],
            "episode_length": self._steps[idx],
            "shortest_path": self._shortest[idx],
            "collisions": self._collisions[idx],
            **{key: column[row] for key, column in self._target_columns.items()},
            "last_view_shows_target": self._tables.visible[row, state],
            "kitchen": np.full(len(idx), self.kitchen, dtype=object),
        }
        if privileged:
            out["state"], out["expert_action"] = state, self._tables.expert[row, state]
        return out

    def _infos(self, names: list[str], idx: np.ndarray) -> dict:
        """The info dicts of agents `names` (rows `idx`), from whole-array gathers."""
        row, state = self._row[idx], self._state[idx]
        meta = self._target_meta
        columns = zip(
            names,
            row.tolist(),
            state.tolist(),
            self._success[idx].tolist(),
            self._path[idx].tolist(),
            self._steps[idx].tolist(),
            self._shortest[idx].tolist(),
            self._collisions[idx].tolist(),
            self._tables.visible[row, state].tolist(),
            self._tables.expert[row, state].tolist(),
        )
        infos, kitchen = {}, self.kitchen
        for a, r, s, success, path, steps, shortest, collisions, shows, expert in columns:
            target, kind, seen = meta[r]
            infos[a] = {
                "success": success,
                "path_length": path,
                "episode_length": steps,
                "shortest_path": shortest,
                "collisions": collisions,
                "target": target,
                "target_kind": kind,
                "target_seen": seen,
                "last_view_shows_target": shows,
                "kitchen": kitchen,
            }
            if self.privileged:
                infos[a]["state"], infos[a]["expert_action"] = s, expert
        return infos

    # -- looking at it ---------------------------------------------------------------------------
    def render(self):
        """rgb_array: the top-down map with every agent of the current episodes and agent 0's path."""
        if self.render_mode is None:
            return None
        if not hasattr(self, "_state"):
            raise EnvError("render() before reset()")
        poses = [self.graph.pose(int(s)) for s in self._state]
        path = [self.graph.pose(s) for s in self._trail] if self._trail else None
        highlight = sorted({self.tasks.targets[r].object_index for r in self._row})
        return top_down_map(self.graph.world, 400, poses, path, highlight)

    def close(self) -> None:
        pass


__all__ = ["NavigationEnv", "parallel_env", "EnvError", "TaskError", "OPEN", "STOP", "ACTIONS"]
