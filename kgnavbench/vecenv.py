"""Stage 8 — vecenv: navigators in many kitchens as one batched simulator, and its Gymnasium faces.

    import gymnasium as gym
    import kgnavbench  # registers the ids below

    envs = gym.make_vec("kgnavbench/train-v0", num_envs=140)  # NavigationVectorEnv: all 20 training kitchens
    observations, infos = envs.reset(seed=0)
    observations, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())

    env = gym.make("kgnavbench/FloorPlan1-v0")  # NavigationGymEnv: one navigator, a gymnasium.Env

Ids: `kgnavbench/FloorPlan1-v0` .. `kgnavbench/FloorPlan30-v0` (one kitchen) and `kgnavbench/train-v0`,
`val-v0`, `test-v0` (a split's kitchens; the navigator's kitchen is drawn per episode, or, vectorised,
sub-env i lives in the split's kitchen i mod K). `gym.make_vec` returns the batched NavigationVectorEnv
itself (its `vector_entry_point`), not copies of the single env.

The semantics are the PettingZoo env's (kgnavbench/env.py), through the same `env.transition`:
Actions: Discrete(10), the paper's order (0 MoveAhead, 1 MoveBack, 2 MoveRight, 3 MoveLeft, 4 RotateRight,
    5 RotateLeft, 6 LookUp, 7 LookDown, 8 OpenObject, 9 Stop); MultiDiscrete for the vector env.
Keywords (both faces, also through gym.make / gym.make_vec / SB3's make_vec_env): kitchens, targets,
    success_rule, stop_ends, max_steps (spec.max_episode_steps reports it; the env truncates there
    itself), curriculum_steps=N (the trainer's start-distance curriculum over the env's first N steps,
    counted in frames: every sub-env's step counts; starts at most `reach` actions from the
    destination, reach growing from 0 to 25, then the training starts), observation ("dict" or "box"),
    views, render_mode ("rgb_array"); the vector env also num_envs and autoreset_mode. An unknown
    keyword is Python's TypeError; an unknown reset option or a bad value is a VecEnvError. A seeded
    reset (a whole number >= 0) starts the env over, its curriculum too: one seed, the same episodes.
Observations (fresh, writable arrays on every call; the vector env's have a leading num_envs axis):
    observation="dict" (default):
    "features"        float32 (512,)  the frozen encoder's features of the current view, standardized
                                      with its statistics of the training kitchens (`encoder.standardize`),
                                      what the learned agents see; bounds -inf..inf
    "target_features" float32 (512,)  the same for the target image (the view at the destination)
    "view_objects"    uint8 (125,)    1 for each object type visible in the current view
    "target_objects"  uint8 (125,)    the same for the target image
    "view", "target"  uint8 (84, 84, 3) the views themselves, with views=True (off by default: 20
                                      kitchens' views take about 1 GB)
    observation="box": one float32 (1274,) vector, BOX_PARTS in this order: features (512),
    view_objects (125), target_features (512), target_objects (125).
Rewards: -0.01 every step; +0.01 the first time a goal state is reached; +10 on success.
Termination: Stop ends the episode (stop_ends=False: a Stop that does not succeed is a no-op); success
    is Stop at the target's destination (success_rule="destination", the paper's) or in any state that
    shows it ("visible"). Truncation at max_steps (5000 by default, as in training).
Episodes: a training target of the kitchen ("seen"; the validation and test kitchens have none, so
    there every target: "all") and a start at pitch 0 at least 10 actions from its destination, drawn
    from the generator seeded by reset(seed=...); reset(options={"reach": N}) draws a start at most N
    actions away instead. The single env also takes reset(options={"target": id, "start": state,
    "max_steps": n}): a given episode.
Autoreset (vector env, `autoreset_mode`): "next_step" (default; gymnasium's NEXT_STEP, what its vector
    wrappers such as NormalizeObservation expect): the step that ends an episode returns its last
    observation; the sub-env's next step starts the next episode, ignoring its action, with reward 0
    and neither terminated nor truncated. "same_step": the ending step returns the next episode's
    first observation, the last one in infos["final_obs"][i] (mask infos["_final_obs"]). "disabled":
    the ending step returns the last observation; the finished sub-envs wait for
    `reset(options={"reset_mask": mask})` (stepping them before is an error). In every mode, every
    step's infos["final_info"] holds the episodes that ended in it (masks False elsewhere): success,
    episode_length, path_length, shortest_path, collisions and episode_return, each with its `_key`
    mask. gym.make_vec's `wrappers=` needs vectorization_mode="sync" (gymnasium refuses wrappers for
    a vector entry point): that builds the vector from single envs; or wrap the returned vector env
    in gymnasium.wrappers.vector's wrappers.
Rendering: render() (render_mode="rgb_array", render_fps 4) gives the egocentric view and the target
    image above the top-down map of the kitchen, the navigator and its target marked; the vector env
    renders its first sub-env.
Infos: every step "kitchen" and "target" (object id) per sub-env. Nothing privileged: no state index,
    no expert action (the PettingZoo env's infos keep those for the shipped plugins and the oracle).

Inside: `StateSpace` concatenates the kitchens' state graphs (global state = kitchen offset + local
state) with per-target goal and distance tables; `Navigators` steps every agent at once as array
gathers. The trainer (kgnavbench/train.py) steps this vector env without autoreset
(`NavigationVectorEnv.over`: its own space, kitchens per sub-env and one target per sub-env): its TSE
reads each agent's state between the step and the reset, and it alone, being the library's trainer,
reads the states themselves (`envs.navigators`) to index its feature tables.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .encoder import FEATURE_DIM, N_TYPES, encoder_feature_stats, standardize, state_features
from .env import (
    MAX_EPISODE_STEPS,
    SUCCESS_RULES,
    TRAINING_MAX_STEPS,
    _is_integer,
    checked_seed,
    transition,
    whole_number_in,
)
from .errors import KgnavbenchError
from .graph import VIEW_SIZE
from .kitchens import KITCHEN_NAMES, check_name, object_types
from .render import top_down_map
from .tasks import KitchenTasks, load_task_file, load_tasks
from .world import ACTIONS

SPLIT_NAMES = ("train", "val", "test")
TARGET_SETS = ("seen", "all")


class VecEnvError(KgnavbenchError, ValueError):
    """Bad input: an unknown kitchen, split, target set or rule; actions of the wrong shape."""


# ------------------------------------------------------------------------------------------------
# 1. The state space: the kitchens' state graphs as one, and navigators stepping in it


@dataclass
class StateSpace:
    """Several kitchens' state graphs as one: global state = kitchen offset + local state."""

    kitchens: list[str]
    offsets: np.ndarray  # (K + 1,)
    next_state: np.ndarray  # (S, 10) global next state per action
    ok: np.ndarray  # (S, 10) the action succeeded
    objects: np.ndarray  # (S, 125) uint8, visible object types
    features: np.ndarray  # (S, F) float16, the frozen encoder's features of each state's view
    kitchen_of: np.ndarray  # (S,)
    closed: np.ndarray  # (S,) no receptacle open
    # targets: one row per target
    target_ids: list[str]
    target_kitchen: np.ndarray  # (T,)
    target_type: np.ndarray  # (T,) object type index
    destination: np.ndarray  # (T,) global state
    goal: np.ndarray  # (T, S) success states under the rule (for the +0.01 and +10)
    visible: np.ndarray  # (T, S) the target is in view
    dist: np.ndarray  # (T, S) int32 BFS actions to a goal state (-1: none)
    start_flat: np.ndarray  # training starts of target t: start_flat[start_ptr[t]:start_ptr[t + 1]]
    start_ptr: np.ndarray
    # a curriculum's starts of target t, nearest first: near_flat[near_ptr[t]:near_ptr[t + 1]], and
    # near_key = t * NEAR_KEY + distance to the destination, sorted, for one searchsorted per draw
    near_flat: np.ndarray
    near_ptr: np.ndarray
    near_key: np.ndarray
    fixed_starts: list[tuple[int, ...]]  # the task file's episodes (global states)
    kitchen_rows: np.ndarray  # target rows of kitchen k: kitchen_rows[kitchen_ptr[k]:kitchen_ptr[k + 1]]
    kitchen_ptr: np.ndarray
    tse_types: np.ndarray  # (K, 125) novel objects: pickupable types that are no target (build_space)
    tasks: list[KitchenTasks] = field(repr=False)
    views: np.ndarray | None = field(default=None, repr=False)  # (S, 84, 84, 3) uint8, pixel models

    @property
    def n_states(self) -> int:
        return len(self.next_state)

    def __post_init__(self) -> None:
        # standardized with the encoder's statistics of the training kitchens (standardize)
        self.features_t = standardize(self.features, encoder_feature_stats())
        self.objects_t = torch.from_numpy(self.objects.astype(np.float32))


def build_space(
    kitchens,
    targets: str = "seen",
    success_rule: str = "destination",
    pixels: bool = False,
    unseen_subtargets: bool = False,
) -> StateSpace:
    """Load the kitchens' state graphs, features and targets ('seen': training targets; 'all'), and
    with `pixels` their views. TSE's novel objects (`tse_types`) are the pickupable types that are no
    training target of the kitchen and, unless `unseen_subtargets`, no unseen target of it either.

    :param kitchens: kitchen names (`FloorPlan1`, ...); the space's kitchen index is their order
    :param targets: 'seen' (the training targets) or 'all' (unseen ones too)
    :param success_rule: how an episode succeeds (`tasks.SUCCESS_RULES`): it decides each target's
        destination states
    :param pixels: also load every state's view (end-to-end training from pixels)
    :param unseen_subtargets: let TSE take the kitchen's unseen targets as sub-targets
    :return: one StateSpace over all the kitchens' states, targets and features
    """
    types = {t: i for i, t in enumerate(object_types())}
    parts, rows, offsets, all_tasks = [], [], [0], []
    tse_types = np.zeros((len(kitchens), len(types)), bool)
    for k, name in enumerate(kitchens):
        kt = load_tasks(name)
        g, off = kt.graph, offsets[-1]
        feats = np.asarray(state_features(name))
        if feats.shape[0] != g.n_states:
            raise VecEnvError(f"features of {name} have {feats.shape[0]} rows for {g.n_states} states")
        chosen = [t for t in kt.targets if targets == "all" or t.seen]
        if not chosen:
            hint = f" (a {kt.split} kitchen: its targets are all unseen; use targets='all')"
            raise VecEnvError(f"{name} has no {targets} targets{hint if targets == 'seen' else ''}")
        training_types = {t.type for t in kt.targets if t.seen}
        held_out = set() if unseen_subtargets else {t.type for t in kt.targets if not t.seen}
        for o in g.world.objects:
            if o.pickupable and o.type not in training_types and o.type not in held_out:
                tse_types[k, types[o.type]] = True
        parts.append((g, feats, kt))
        rows += [(k, off, kt, t) for t in chosen]
        offsets.append(off + g.n_states)
        all_tasks.append(kt)
    n = offsets[-1]
    n_targets = len(rows)
    goal = np.zeros((n_targets, n), bool)
    visible = np.zeros((n_targets, n), bool)
    dist = np.full((n_targets, n), -1, np.int32)
    starts, start_ptr, fixed = [], [0], []
    near, near_ptr, near_key = [], [0], []
    for r, (_, off, kt, t) in enumerate(rows):
        g = kt.graph
        m = g.n_states
        visible[r, off + np.array(t.goal_states)] = True
        goal[r, off + np.array(t.goals(success_rule))] = True
        dist[r, off : off + m] = kt.distances(t, success_rule)
        far = kt.training_starts(t)  # the env draws its training starts from the same states
        starts.append(far + off)
        start_ptr.append(start_ptr[-1] + len(far))
        fixed.append(tuple(int(s) + off for s in t.starts))
        ladder, ladder_dist = kt.curriculum_starts(t)
        near.append(ladder + off)
        near_ptr.append(near_ptr[-1] + len(ladder))
        near_key.append(r * NEAR_KEY + ladder_dist)
    target_kitchen = np.array([r[0] for r in rows], np.int64)
    order = np.argsort(target_kitchen, kind="stable")
    return StateSpace(
        kitchens=list(kitchens),
        offsets=np.array(offsets, np.int64),
        next_state=np.concatenate([g.next_state + off for (g, _, _), off in zip(parts, offsets)]),
        ok=np.concatenate([g.ok for g, _, _ in parts]),
        objects=np.concatenate([g.object_vectors for g, _, _ in parts]),
        features=np.concatenate([f for _, f, _ in parts]),
        views=np.concatenate([g.views for g, _, _ in parts]) if pixels else None,
        kitchen_of=np.repeat(np.arange(len(kitchens)), np.diff(offsets)),
        closed=np.concatenate([g.opened < 0 for g, _, _ in parts]),
        target_ids=[t.object_id for _, _, _, t in rows],
        target_kitchen=target_kitchen,
        target_type=np.array([types[t.type] for _, _, _, t in rows], np.int64),
        destination=np.array([off + t.destination for _, off, _, t in rows], np.int64),
        goal=goal,
        visible=visible,
        dist=dist,
        start_flat=np.concatenate(starts).astype(np.int64),
        start_ptr=np.array(start_ptr, np.int64),
        near_flat=np.concatenate(near).astype(np.int64),
        near_ptr=np.array(near_ptr, np.int64),
        near_key=np.concatenate(near_key).astype(np.int64),
        fixed_starts=fixed,
        kitchen_rows=order.astype(np.int64),
        kitchen_ptr=np.searchsorted(target_kitchen[order], np.arange(len(kitchens) + 1)).astype(np.int64),
        tse_types=tse_types,
        tasks=all_tasks,
    )


NEAR_KEY = 1 << 20  # larger than any BFS distance
CURRICULUM_REACH = 25  # actions: about the farthest training start (they lie 10-25 from the destination)


def arrays_state(owner, fields) -> dict:
    """A checkpoint's copy of an object's NumPy arrays, as tensors (weights_only loads them)."""
    return {name: torch.from_numpy(getattr(owner, name).copy()) for name in fields}


def load_arrays(owner, fields, d: dict, what: str) -> None:
    """Put back what `arrays_state` saved; a shape that differs is a ValueError naming the field."""
    for name in fields:
        value = d[name].numpy()
        if value.shape != getattr(owner, name).shape:
            raise ValueError(f"{what} {name} has shape {value.shape}, expected {getattr(owner, name).shape}")
        setattr(owner, name, value.copy())


class Navigators:
    """Agents in a StateSpace, each in its own episode: env.step for all of them as array gathers.
    A finished agent stays where it is until the caller starts its next episode (`draw`/`begin`)."""

    FIELDS = (
        "kitchen", "target", "state", "start", "steps", "path", "collisions", "success", "arrived", "cap",
        "episode_return",
    )  # fmt: skip

    def __init__(
        self,
        space: StateSpace,
        kitchen: np.ndarray,
        stop_ends: bool = True,
        assigned: np.ndarray | None = None,
        success_rule: str = "destination",  # the rule `space.goal` was built for (`tasks.outcome`)
    ):
        n = len(kitchen)
        self.space, self.stop_ends, self.n = space, stop_ends, n
        self.success_rule = success_rule
        self.kitchen = np.asarray(kitchen, np.int64).copy()
        # each agent's own target row (the paper's one target per thread); None: drawn per episode
        self.assigned = None if assigned is None else np.asarray(assigned, np.int64).copy()
        for name in ("target", "state", "start", "steps", "path", "collisions", "cap"):
            setattr(self, name, np.zeros(n, np.int64))
        self.success = np.zeros(n, bool)
        self.arrived = np.zeros(n, bool)
        self.episode_return = np.zeros(n, np.float64)

    def begin(self, idx: np.ndarray, targets: np.ndarray, starts: np.ndarray, caps) -> None:
        """Start episodes: agents idx get these targets (rows), start states and caps."""
        self.target[idx], self.state[idx], self.start[idx], self.cap[idx] = targets, starts, starts, caps
        for name in ("steps", "path", "collisions"):
            getattr(self, name)[idx] = 0
        self.success[idx] = False
        self.arrived[idx] = self.space.goal[targets, starts]
        self.episode_return[idx] = 0.0

    def draw(self, idx: np.ndarray, rng: np.random.Generator, cap: int, reach: int | None = None) -> None:
        """Training episodes as the env draws them: the agent's own target (or, without assigned
        targets, one of its kitchen's), then a start; with `reach`, a distance in 0..reach drawn
        uniformly, then a start at that distance from the destination (or the nearest distance below
        it that has one), so near starts stay frequent."""
        sp = self.space
        if self.assigned is not None:
            targets = self.assigned[idx]
        else:
            k = self.kitchen[idx]
            lo = sp.kitchen_ptr[k]
            targets = sp.kitchen_rows[lo + rng.integers(0, sp.kitchen_ptr[k + 1] - lo)]
        if reach is None:
            lo = sp.start_ptr[targets]
            starts = sp.start_flat[lo + rng.integers(0, sp.start_ptr[targets + 1] - lo)]
        else:  # a reach beyond every distance is every start (and must not spill into the next key)
            key = targets * NEAR_KEY + rng.integers(0, min(reach, NEAR_KEY - 1) + 1, len(targets))
            hi = np.maximum(np.searchsorted(sp.near_key, key, "right"), sp.near_ptr[targets] + 1)
            lo = np.searchsorted(sp.near_key, sp.near_key[hi - 1], "left")
            starts = sp.near_flat[lo + rng.integers(0, hi - lo)]
        self.begin(idx, targets, starts, cap)

    def step(self, actions: np.ndarray, idx: np.ndarray | None = None):
        """One action per agent (of idx, or all): rewards, terminated, truncated, as env.step."""
        sel = slice(None) if idx is None else idx
        sp = self.space
        t = transition(
            sp.next_state,
            sp.ok,
            sp.goal,
            self.state[sel],
            actions,
            self.target[sel],
            self.arrived[sel],
            self.steps[sel],
            self.cap[sel],
            self.stop_ends,
            self.success_rule,
        )
        self.state[sel] = t.next_state
        self.steps[sel] += 1
        self.path[sel] += ~t.stop
        self.collisions[sel] += t.collided
        self.arrived[sel] |= t.on_goal
        self.success[sel] = t.success
        self.episode_return[sel] += t.reward
        return t.reward, t.terminated, t.truncated

    def state_dict(self) -> dict:
        return arrays_state(self, self.FIELDS)

    def load_state_dict(self, d: dict) -> None:
        load_arrays(self, self.FIELDS, d, "agents'")


# ------------------------------------------------------------------------------------------------
# 2. The Gymnasium faces


def kitchens_of(kitchens) -> list[str]:
    """'train' | 'val' | 'test' -> that split's kitchens; a kitchen name -> [it]; a list -> itself."""
    if isinstance(kitchens, str):
        if kitchens in SPLIT_NAMES:
            return sorted(load_task_file()["splits"][kitchens], key=KITCHEN_NAMES.index)
        kitchens = [kitchens]
    names = list(kitchens)
    if not names:
        raise VecEnvError("no kitchens given")
    for name in names:
        try:
            check_name(name)
        except ValueError as e:
            raise VecEnvError(f"{e} (or a split: {', '.join(SPLIT_NAMES)})") from e
    return names


def default_targets(kitchens: list[str]) -> str:
    """'seen' (the training targets) where every kitchen is a training kitchen, else 'all'."""
    train = set(load_task_file()["splits"]["train"])
    return "seen" if set(kitchens) <= train else "all"


OBSERVATIONS = ("dict", "box")
AUTORESET_MODES = {
    "next_step": AutoresetMode.NEXT_STEP,
    "same_step": AutoresetMode.SAME_STEP,
    "disabled": AutoresetMode.DISABLED,
}
RENDER_FPS = 4  # frames per second of render()'s pictures (gymnasium's HumanRendering, videos)
BOX_PARTS = ("features", "view_objects", "target_features", "target_objects")  # the flat Box's order


def curriculum_reach(done: float, over: float) -> int | None:
    """The start-distance curriculum: the farthest start (actions from the destination) after `done`
    of its `over` frames, growing from 0 to CURRICULUM_REACH; None once it is over (or off, over = 0):
    the training starts, 10-25 actions away. The trainer's (`start_curriculum`) and the envs'
    (`curriculum_steps`)."""
    if not over or done >= over:
        return None
    return int(CURRICULUM_REACH * done / over)


def observation_space(
    views: bool = False, view_size: int = VIEW_SIZE, observation: str = "dict"
) -> spaces.Space:
    """One navigator's observation space (the module docstring). The standardized features have no
    bounds of their own (the encoder's ReLU features, standardized): -inf .. inf. observation="box":
    one float32 vector, BOX_PARTS in that order (512 + 125 + 512 + 125 = 1274 numbers)."""
    features = spaces.Box(-np.inf, np.inf, (FEATURE_DIM,), np.float32)
    objects = spaces.Box(0, 1, (N_TYPES,), np.uint8)
    if observation == "box":
        half_low = np.concatenate([np.full(FEATURE_DIM, -np.inf), np.zeros(N_TYPES)]).astype(np.float32)
        half_high = np.concatenate([np.full(FEATURE_DIM, np.inf), np.ones(N_TYPES)]).astype(np.float32)
        return spaces.Box(np.concatenate([half_low, half_low]), np.concatenate([half_high, half_high]))
    parts = {"features": features, "target_features": features, "view_objects": objects}
    parts["target_objects"] = objects
    if views:
        parts["view"] = spaces.Box(0, 255, (view_size, view_size, 3), np.uint8)
        parts["target"] = spaces.Box(0, 255, (view_size, view_size, 3), np.uint8)
    return spaces.Dict(parts)


# an upper bound that names the limit rather than fill the memory: 140 envs train Table I's rows
MAX_ENVS = 4096


class Navigation:
    """What both faces share: the space, the navigators, the observation gathers, the infos, the
    curriculum and the spec (`spec.max_episode_steps` is the env's max_steps)."""

    _spec = None

    @property
    def spec(self):
        """gymnasium's EnvSpec of a registered id (gym.make sets it), with max_episode_steps the env's
        max_steps: the env truncates there itself, so no TimeLimit wrapper is needed (or added)."""
        if self._spec is None:
            return None
        import dataclasses

        return dataclasses.replace(self._spec, max_episode_steps=self.max_steps)

    @spec.setter
    def spec(self, value) -> None:
        """gym.make sets the spec it made the env from: it must agree with the env. A registered id
        names its kitchens: a kitchens= keyword may not replace them. (gym.make's max_episode_steps
        adds gymnasium's TimeLimit around the env after this, out of its reach: docs/environments.md.)"""
        if value is not None:
            from gymnasium.envs.registration import registry

            registered = registry.get(value.id)
            kitchens = (registered.kwargs or {}).get("kitchens") if registered is not None else None
            if kitchens is not None and (value.kwargs or {}).get("kitchens", kitchens) != kitchens:
                raise VecEnvError(
                    f"{value.id} is the kitchens {kitchens!r}; kitchens={value.kwargs['kitchens']!r} "
                    "cannot replace them (make the id of those kitchens instead)"
                )
        self._spec = value

    def _setup(
        self, n, kitchens, targets, success_rule, stop_ends, max_steps, views, observation="dict"
    ) -> None:
        """The constructors' shared set-up: the options checked, the state space built for these
        kitchens and target set, n navigators spread over the kitchens in turn."""
        names = kitchens_of(kitchens)
        targets = default_targets(names) if targets is None else targets
        if targets not in TARGET_SETS:
            raise VecEnvError(f"unknown target set {targets!r}; choose one of {', '.join(TARGET_SETS)}")
        if success_rule not in SUCCESS_RULES:
            raise VecEnvError(f"unknown success_rule {success_rule!r}; choose one of {SUCCESS_RULES}")
        if observation not in OBSERVATIONS:
            raise VecEnvError(f"unknown observation {observation!r}; choose one of {OBSERVATIONS}")
        if views and observation == "box":
            raise VecEnvError("views=True needs observation='dict' (the flat Box holds no pixels)")
        for name, value in (("stop_ends", stop_ends), ("views", views)):
            if not isinstance(value, (bool, np.bool_)):  # "false" is a true string
                raise VecEnvError(f"{name} must be True or False, not {value!r}")
        space = build_space(names, targets, success_rule, pixels=views)
        if success_rule == "arrival" and stop_ends:
            raise VecEnvError("success_rule='arrival' makes Stop a no-op: pass stop_ends=False")
        kitchen = np.arange(n) % len(names)
        navigators = Navigators(space, kitchen, stop_ends=bool(stop_ends), success_rule=success_rule)
        self._use(navigators, max_steps, views, observation)

    def _use(self, navigators: Navigators, max_steps, views: bool, observation: str = "dict") -> None:
        """Take `navigators` (and their state space) as this env's agents, with the episode cap and
        what an observation holds."""
        max_steps = whole_number_in(max_steps, "max_steps", 1, MAX_EPISODE_STEPS, VecEnvError)
        if views and navigators.space.views is None:
            raise VecEnvError("views=True needs a state space built with its views (pixels=True)")
        self.space, self.navigators = navigators.space, navigators
        self.views, self.observation = views, observation
        self.max_steps = max_steps
        self.curriculum_steps, self.curriculum_done = 0, 0
        # the learned agents' inputs as plain float32 rows, gathered per step into fresh arrays
        self._features = self.space.features_t.numpy()
        self._kitchen_names = np.array(self.space.kitchens, dtype=object)
        self._target_names = np.array(self.space.target_ids, dtype=object)

    def _curriculum(self, steps) -> None:
        """Set the start curriculum's length in steps (0: none), checked."""
        if not _is_integer(steps) or steps < 0:
            raise VecEnvError(f"curriculum_steps must be a whole number of steps >= 0, not {steps!r}")
        self.curriculum_steps = int(steps)

    def reach(self) -> int | None:
        """The curriculum's farthest start now (None: no curriculum, or it is over)."""
        return curriculum_reach(self.curriculum_done, self.curriculum_steps)

    def _gather(self, idx=slice(None)) -> dict | np.ndarray:
        """The observations of the agents `idx`: view and target features and object vectors (and
        views), as a dict of arrays or one float32 Box row each."""
        sp, nav = self.space, self.navigators
        state, goal = nav.state[idx], sp.destination[nav.target[idx]]
        if self.observation == "box":
            f, objects = self._features, sp.objects
            parts = (f[state], objects[state], f[goal], objects[goal])
            return np.concatenate(parts, axis=-1, dtype=np.float32)
        out = {
            "features": self._features[state],
            "target_features": self._features[goal],
            "view_objects": sp.objects[state],
            "target_objects": sp.objects[goal],
        }
        if self.views:
            out["view"], out["target"] = sp.views[state], sp.views[goal]
        return out

    def _episode_info(self, idx) -> dict:
        """The ended episodes' numbers of the agents `idx`: success, lengths, shortest path,
        collisions, return."""
        nav = self.navigators
        return {
            "success": nav.success[idx].copy(),
            "episode_length": nav.steps[idx].copy(),
            "path_length": nav.path[idx].copy(),
            "shortest_path": self.space.dist[nav.target[idx], nav.start[idx]].astype(np.int64),
            "collisions": nav.collisions[idx].copy(),
            "episode_return": nav.episode_return[idx].copy(),
        }

    def _picture(self, i: int) -> np.ndarray:
        """Navigator i as render() shows it: its egocentric view and the target image (the view at the
        destination) above the top-down map of its kitchen, with it and its target marked."""
        import cv2

        sp, nav = self.space, self.navigators
        k = int(nav.kitchen[i])
        graph = sp.tasks[k].graph
        local = int(nav.state[i] - sp.offsets[k])
        destination = int(sp.destination[nav.target[i]] - sp.offsets[k])
        target = sp.tasks[k].target(sp.target_ids[nav.target[i]])
        top = top_down_map(graph.world, 400, [graph.pose(local)], None, [target.object_index])
        views = [np.asarray(graph.views[s]) for s in (local, destination)]
        views = [cv2.resize(v, (200, 200), interpolation=cv2.INTER_NEAREST) for v in views]
        for v, label in zip(views, ("view", "target"), strict=True):
            cv2.putText(v, label, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
        return np.ascontiguousarray(np.concatenate([np.concatenate(views, axis=1), top], axis=0))


class NavigationVectorEnv(Navigation, VectorEnv):
    """num_envs navigators over `kitchens` (a split, a kitchen or a list), sub-env i in kitchen i mod K,
    stepped at once; gymnasium's VectorEnv. See the module docstring for the keywords."""

    metadata = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
        "render_fps": RENDER_FPS,
    }
    _observe = True  # reset and step gather the observations (`over(..., observe=False)`: they don't)

    def __init__(
        self,
        num_envs: int = 140,
        kitchens="train",
        targets: str | None = None,
        success_rule: str = "destination",
        stop_ends: bool = True,
        max_steps: int = TRAINING_MAX_STEPS,
        views: bool = False,
        autoreset_mode: str | AutoresetMode = "next_step",
        curriculum_steps: int = 0,
        observation: str = "dict",
        render_mode: str | None = None,
    ):
        num_envs = whole_number_in(num_envs, "num_envs", 1, MAX_ENVS, VecEnvError)
        if render_mode not in (None, "rgb_array"):
            raise VecEnvError(f"unknown render_mode {render_mode!r}; choose None or 'rgb_array'")
        self.render_mode = render_mode
        mode = _autoreset_mode(autoreset_mode)
        self._setup(num_envs, kitchens, targets, success_rule, stop_ends, max_steps, views, observation)
        self._curriculum(curriculum_steps)
        self._spaces(mode)

    @classmethod
    def over(
        cls,
        space: StateSpace,
        kitchen: np.ndarray,
        assigned: np.ndarray | None = None,
        stop_ends: bool = True,
        max_steps: int = TRAINING_MAX_STEPS,
        autoreset_mode: str | AutoresetMode = "next_step",
        observe: bool = True,
    ) -> NavigationVectorEnv:
        """The vector env over a state space already built (`build_space`), sub-env i in the space's
        kitchen `kitchen[i]` and, with `assigned`, keeping target row `assigned[i]` in every episode:
        the trainer's layout (the paper's threads, one training target each). observe=False: reset and
        step return None for the observations (the trainer reads the states; gathering the feature
        rows it never uses cost about 5% of an update)."""
        env = cls.__new__(cls)
        env.render_mode = None
        mode = _autoreset_mode(autoreset_mode)
        env._use(Navigators(space, kitchen, stop_ends=bool(stop_ends), assigned=assigned), max_steps, False)
        env._spaces(mode)
        env._observe = bool(observe)
        return env

    def _spaces(self, mode: AutoresetMode) -> None:
        self.num_envs = n = self.navigators.n
        self.autoreset_mode = mode
        self.metadata = {**type(self).metadata, "autoreset_mode": mode}
        self.single_observation_space = observation_space(self.views, observation=self.observation)
        self.single_action_space = spaces.Discrete(len(ACTIONS))
        self.observation_space = batch_space(self.single_observation_space, n)
        self.action_space = batch_space(self.single_action_space, n)
        self._all = np.arange(n)
        self._ended = np.zeros(n, bool)  # DISABLED: finished, waiting for a reset
        self._pending = np.zeros(n, bool)  # NEXT_STEP: finished; the next step starts its next episode
        self._reset_once = False

    @property
    def stop_ends(self) -> bool:
        """Whether a Stop that does not succeed ends the episode (False: a no-op); settable between steps."""
        return self.navigators.stop_ends

    @stop_ends.setter
    def stop_ends(self, value: bool) -> None:
        self.navigators.stop_ends = bool(value)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """New episodes for every sub-env, or (options["reset_mask"], a bool per sub-env) for those only;
        options["reach"]: starts at most that many actions from the destination (else the curriculum's,
        with curriculum_steps). A seed starts the env over: its curriculum too, so that the same seed
        gives the same episodes."""
        if seed is not None:
            seed = checked_seed(seed, VecEnvError)
            self.np_random = np.random.default_rng(seed)
            self.single_action_space.seed(seed)
            self.action_space.seed(seed)
            self.curriculum_done = 0
        if options is not None and not isinstance(options, dict):
            raise VecEnvError(f"options must be a dict, not {type(options).__name__}")
        options = dict(options or {})
        mask, reach = options.pop("reset_mask", None), options.pop("reach", None)
        if options:
            raise VecEnvError(f"unknown reset options {sorted(map(str, options))}; known: reset_mask, reach")
        idx = self._all
        if mask is not None:
            mask = np.asarray(mask)
            if mask.shape != (self.num_envs,) or mask.dtype != bool:
                raise VecEnvError(f"reset_mask must be {self.num_envs} bools, got {mask.dtype} {mask.shape}")
            idx = np.flatnonzero(mask)
        if reach is not None and (not _is_integer(reach) or reach < 0):
            raise VecEnvError(f"reach must be a whole number of actions >= 0, not {reach!r}")
        reach = self.reach() if reach is None else int(reach)
        self.navigators.draw(idx, self.np_random, self.max_steps, reach)
        self._ended[idx] = self._pending[idx] = False
        self._reset_once = True
        return self._gather() if self._observe else None, self._infos()

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs,) or not np.issubdtype(actions.dtype, np.integer):
            raise VecEnvError(
                f"actions must be {self.num_envs} integers, got {actions.dtype} {actions.shape}"
            )
        if actions.min() < 0 or actions.max() >= len(ACTIONS):
            raise VecEnvError(f"actions must lie in 0..{len(ACTIONS) - 1}")
        if not self._reset_once:
            raise VecEnvError("step() before reset(): reset the env first")
        if self._ended.any():
            raise VecEnvError(
                f"sub-envs {np.flatnonzero(self._ended).tolist()[:10]} finished their episodes: without "
                "autoreset, reset them first (reset(options={'reset_mask': mask}))"
            )
        n = self.num_envs
        rewards, terminated, truncated = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        restarting = np.flatnonzero(self._pending)  # NEXT_STEP: their action is ignored; a new episode
        if len(restarting):
            self.navigators.draw(restarting, self.np_random, self.max_steps, self.reach())
            self._pending[restarting] = False
            going = np.flatnonzero(~np.isin(self._all, restarting))
            r, term, trunc = self.navigators.step(actions[going].astype(np.int64), going)
            rewards[going], terminated[going], truncated[going] = r, term, trunc
        else:
            going = self._all
            rewards, terminated, truncated = self.navigators.step(actions.astype(np.int64))
        self.curriculum_done += len(going)
        done = np.flatnonzero(terminated | truncated)
        infos = self._infos()
        # every step has final_info (masks all False where nothing ended): no KeyError in a loop
        mask = np.zeros(n, bool)
        mask[done] = True
        final_info = {}
        for key, value in self._episode_info(done).items():
            column = np.zeros(n, value.dtype)
            column[done] = value
            final_info[key], final_info[f"_{key}"] = column, mask.copy()
        infos.update(final_info=final_info, _final_info=mask)
        if len(done):
            if self.autoreset_mode == AutoresetMode.SAME_STEP:
                last = self._gather(done)
                final_obs = np.full(n, None, dtype=object)
                for j, i in enumerate(done.tolist()):
                    final_obs[i] = (
                        last[j] if self.observation == "box" else {k: v[j] for k, v in last.items()}
                    )
                infos.update(final_obs=final_obs, _final_obs=mask.copy())
                self.navigators.draw(done, self.np_random, self.max_steps, self.reach())
            elif self.autoreset_mode == AutoresetMode.NEXT_STEP:
                self._pending[done] = True
            else:
                self._ended[done] = True
        return (
            self._gather() if self._observe else None,
            np.asarray(rewards, np.float64),
            np.asarray(terminated, bool).copy(),
            np.asarray(truncated, bool).copy(),
            infos,
        )

    def render(self):
        """rgb_array: the first sub-env (its view and target image above its kitchen's map)."""
        if self.render_mode is None:
            return None
        if not self._reset_once:
            raise VecEnvError("render() before reset()")
        return self._picture(0)

    def _infos(self) -> dict:
        nav = self.navigators
        every = np.ones(self.num_envs, bool)
        return {
            "kitchen": self._kitchen_names[nav.kitchen],
            "_kitchen": every,
            "target": self._target_names[nav.target],
            "_target": every.copy(),
        }


def _autoreset_mode(mode) -> AutoresetMode:
    if isinstance(mode, AutoresetMode):
        return mode
    if isinstance(mode, str) and mode.lower() in AUTORESET_MODES:
        return AUTORESET_MODES[mode.lower()]
    raise VecEnvError(f"unknown autoreset_mode {mode!r}; choose one of {', '.join(AUTORESET_MODES)}")
