"""Stage 4 — tasks: the discrete state graph of a kitchen, targets, splits, fixed episodes, shortest
paths and expert trajectories.

State graph. A state is (cell, heading, pitch, open receptacle or none) — DESIGN.md's finite set.
Closed states are every reachable cell x 4 headings x 4 pitches, numbered ((cell * 4 + heading) * 4 +
pitch). OpenObject in a closed state opens the receptacle that the view there picks (nearest the image
centre), so each closed state has at most one open twin, numbered after all closed states. An open
state behaves like its closed twin for every action but Stop (which keeps it open) and OpenObject
(which closes and reopens the same receptacle): the auto-close rule. Transitions come from stepping
the world itself; each state also stores what is visible there and its 84x84 view, so an environment
step is an array lookup. Built once per kitchen and cached on disk (`cache_dir()`).

Targets (per kitchen, AI2-THOR start scene):
  * static: an object of an eligible type — pickupable, or one of COMMON_ITEMS — visible from some
    closed state;
  * actionable: an object hidden inside a closed openable receptacle at the start, visible from some
    open state (its receptacle open).
Goal states of a target are the states where it is visible; its destination is the goal state nearest
the object (ties: more pixels, then the lowest state index), and its target image is the view there.

Splits (rules in code here, written down in the README):
  * kitchens: the 20 with the most actionable targets train (ties: the lower FloorPlan number); the
    other ten, in the same order, alternate validation and test;
  * targets: a training kitchen has SEEN_TARGETS_PER_KITCHEN (7) seen targets, the paper's 140 in 20
    kitchens: every actionable target, then static ones by a shuffle seeded with the kitchen name
    (`seen_targets`); its other targets are unseen. Every target of a validation or test kitchen is
    unseen.
Fixed episodes: 100 per target, starting in a closed state at pitch 0 that does not show the target,
at least 10 actions from the target's destination (the place its image shows), drawn with a generator
seeded by "<kitchen>/<object id>". They are saved in `kgnavbench/data/tasks.json.gz` (committed;
`make tasks` rebuilds it) and are the same for every method.

Shortest paths: multi-source BFS over the reversed transition table, one vectorised frontier
expansion per level (no Python loop per node). Experts: the BFS-optimal one (first action in the
paper's order that lowers the distance) and the paper's (walk back from the destination with
MoveBack / MoveLeft / RotateRight by priority, then reverse).
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import json
import os
import random
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from .files import atomic_write
from .kitchens import (
    DATA_DIR,
    KITCHEN_DIR,
    KITCHEN_NAMES,
    check_name,
    object_types,
)
from .render import Visibility, render_views, visibility
from .world import ACTIONS, HEADINGS, PITCHES, Pose, World

# Household items that count as static targets although they cannot be picked up.
COMMON_ITEMS = (
    "CoffeeMachine",
    "Faucet",
    "Fridge",
    "GarbageCan",
    "HousePlant",
    "LightSwitch",
    "Microwave",
    "Sink",
    "StoveBurner",
    "Toaster",
)
OPEN = ACTIONS.index("OpenObject")
STOP = ACTIONS.index("Stop")
MOVES = tuple(ACTIONS.index(a) for a in ("MoveAhead", "MoveBack", "MoveRight", "MoveLeft"))
VIEW_SIZE = 84
GRAPH_VERSION = 2  # bump when build_state_graph changes what it produces
N_TRAIN_KITCHENS, N_VAL_KITCHENS = 20, 5
SUCCESS_RULES = ("visible", "destination")  # see Target.goals
SEEN_TARGETS_PER_KITCHEN = 7  # the paper: 140 training targets in 20 training kitchens
EPISODES_PER_TARGET = 100
MIN_START_DISTANCE = 10
START_PITCH = 0
TASKS_FILE = DATA_DIR / "tasks.json.gz"
TASKS_FORMAT = 2  # 2: the paper's target split (7 seen per training kitchen, actionable first)
# The paper's walk-back expert: from the destination try these in order, then reverse the walk.
WALK_BACK_PRIORITY = ("MoveBack", "MoveLeft", "RotateRight")
REVERSE = {"MoveBack": "MoveAhead", "MoveLeft": "MoveRight", "RotateRight": "RotateLeft"}


class TaskError(ValueError):
    """Bad task input: unknown target, stale or corrupt task file, unreachable destination."""


# ------------------------------------------------------------------------------------------------
# The state graph


@dataclass
class StateGraph:
    """Every state of one kitchen (start scene) with its transitions, what is visible and its view."""

    kitchen: str
    world: World
    cells: list[tuple[int, int]]
    cell: np.ndarray  # (S,) index into cells
    heading: np.ndarray  # (S,) degrees
    pitch: np.ndarray  # (S,) degrees
    opened: np.ndarray  # (S,) object index of the open receptacle, -1 for none
    next_state: np.ndarray  # (S, 10) the state each action leads to (ACTIONS order)
    ok: np.ndarray  # (S, 10) whether the action succeeds (False: a collision or a failed action)
    visible: list[Visibility]  # (S,)
    views: np.ndarray  # (S, V, V, 3) uint8 RGB, the view of every state
    object_vectors: np.ndarray = field(init=False)  # (S, 125) uint8: which object types are visible

    def __post_init__(self) -> None:
        types = {t: i for i, t in enumerate(object_types())}
        vectors = np.zeros((self.n_states, len(types)), np.uint8)
        type_index = [types[o.type] for o in self.world.objects]
        for s, v in enumerate(self.visible):
            vectors[s, [type_index[i] for i in v.visible]] = 1
        self.object_vectors = vectors
        # observations are views into these arrays: nobody may write through them
        self.object_vectors.flags.writeable = False
        if self.views.flags.writeable:
            self.views.flags.writeable = False

    @property
    def n_states(self) -> int:
        return len(self.cell)

    @property
    def n_closed(self) -> int:
        return len(self.cells) * len(HEADINGS) * len(PITCHES)

    def pose(self, s: int) -> Pose:
        return Pose(self.cells[self.cell[s]], int(self.heading[s]), int(self.pitch[s]))

    def state_of(self, pose: Pose, opened: int = -1) -> int:
        closed = self._closed_index(
            self.cells.index(pose.cell), HEADINGS.index(pose.heading), PITCHES.index(pose.pitch)
        )
        if opened < 0:
            return closed
        s = int(self.next_state[closed, OPEN])
        if self.opened[s] != opened:
            raise TaskError(f"OpenObject at {pose} does not open object {opened}")
        return s

    @staticmethod
    def _closed_index(ci: int, hi: int, pi: int) -> int:
        return (ci * len(HEADINGS) + hi) * len(PITCHES) + pi

    def visible_mask(self, object_index: int) -> np.ndarray:
        return np.array([object_index in v.visible for v in self.visible])


def build_state_graph(world: World, view_size: int = VIEW_SIZE) -> StateGraph:
    """Enumerate the states, step the world for every (state, action), record visibility and views."""
    world.close()
    cells = list(world.kitchen.reachable)
    closed = [Pose(c, h, p) for c in cells for h in HEADINGS for p in PITCHES]
    n_closed = len(closed)
    vis = visibility(world, closed)
    views = [_render(world, closed, view_size)]
    index = {pose: i for i, pose in enumerate(closed)}

    # open twins: one per closed state whose view has an openable receptacle to open
    twin = np.full(n_closed, -1, np.int64)
    open_states: list[tuple[int, int]] = []  # (closed state, receptacle index)
    for s, v in enumerate(vis):
        if v.open_target is not None:
            twin[s] = n_closed + len(open_states)
            open_states.append((s, world.index(v.open_target)))
    open_vis: list[Visibility | None] = [None] * len(open_states)
    open_views = np.zeros((len(open_states), view_size, view_size, 3), np.uint8)
    by_receptacle: dict[int, list[int]] = {}
    for k, (_, r) in enumerate(open_states):
        by_receptacle.setdefault(r, []).append(k)
    for r, ks in by_receptacle.items():
        world.open(world.objects[r].id)
        poses = [closed[open_states[k][0]] for k in ks]
        for k, v in zip(ks, visibility(world, poses)):
            open_vis[k] = v
        open_views[ks] = _render(world, poses, view_size)
        world.close()
    views.append(open_views)

    n = n_closed + len(open_states)
    nxt = np.zeros((n, len(ACTIONS)), np.int64)
    ok = np.zeros((n, len(ACTIONS)), bool)
    for s, pose in enumerate(closed):
        for a, action in enumerate(ACTIONS):
            if a == OPEN:
                nxt[s, a] = twin[s] if twin[s] >= 0 else s
                ok[s, a] = twin[s] >= 0
                continue
            world.teleport(pose)
            result = world.step(action)
            nxt[s, a] = index[result.pose]
            ok[s, a] = result.success
    for k, (s, _) in enumerate(open_states):
        o = n_closed + k
        nxt[o], ok[o] = nxt[s], ok[s]
        nxt[o, STOP] = o  # Stop keeps the receptacle open
        nxt[o, OPEN], ok[o, OPEN] = o, True  # closes, then reopens the same receptacle
    world.teleport(closed[0])

    cell_index = {c: i for i, c in enumerate(cells)}
    base = [closed[s] for s, _ in open_states]
    return StateGraph(
        kitchen=world.kitchen.name,
        world=world,
        cells=cells,
        cell=np.array([cell_index[p.cell] for p in closed + base], np.int64),
        heading=np.array([p.heading for p in closed + base], np.int64),
        pitch=np.array([p.pitch for p in closed + base], np.int64),
        opened=np.array([-1] * n_closed + [r for _, r in open_states], np.int64),
        next_state=nxt,
        ok=ok,
        visible=list(vis) + open_vis,
        views=np.concatenate(views),
    )


def _render(world: World, poses: list[Pose], size: int, batch: int = 64) -> np.ndarray:
    out = np.zeros((len(poses), size, size, 3), np.uint8)
    for start in range(0, len(poses), batch):
        out[start : start + batch] = render_views(world, poses[start : start + batch], size)[0]
    return out


# ------------------------------------------------------------------------------------------------
# The on-disk cache of state graphs (derived data: a corrupt or stale file is rebuilt, never trusted)


def cache_dir() -> Path:
    """$KGNAVBENCH_CACHE, else $XDG_CACHE_HOME/kgnavbench, else ~/.cache/kgnavbench."""
    if os.environ.get("KGNAVBENCH_CACHE"):
        return Path(os.environ["KGNAVBENCH_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "kgnavbench"


@cache
def graph_fingerprint(kitchen: str) -> str:
    """Changes whenever the kitchen file or the code that makes states, transitions and views does."""
    h = hashlib.sha256(f"graph-{GRAPH_VERSION}".encode())
    h.update((KITCHEN_DIR / f"{kitchen}.json.gz").read_bytes())
    for stage in ("world.py", "render.py"):
        h.update((Path(__file__).parent / stage).read_bytes())
    return h.hexdigest()[:16]


def _cache_paths(kitchen: str, view_size: int, root: Path) -> tuple[Path, Path]:
    stem = root / f"{kitchen}-{graph_fingerprint(kitchen)}"
    return stem.with_suffix(".graph.npz"), Path(f"{stem}.views{view_size}.npy")


def save_graph(graph: StateGraph, root: Path) -> None:
    graph_path, views_path = _cache_paths(graph.kitchen, graph.views.shape[1], root)
    vis_ptr = np.cumsum([0] + [len(v.visible) for v in graph.visible])
    open_target = [graph.world.index(v.open_target) if v.open_target else -1 for v in graph.visible]
    arrays = dict(
        cells=np.array(graph.cells, np.int64),
        cell=graph.cell,
        heading=graph.heading,
        pitch=graph.pitch,
        opened=graph.opened,
        next=graph.next_state,
        ok=graph.ok,
        vis_ptr=vis_ptr,
        vis_obj=np.array([i for v in graph.visible for i in v.visible], np.int64),
        vis_pixels=np.array([p for v in graph.visible for p in v.pixels], np.int64),
        open_target=np.array(open_target, np.int64),
    )
    atomic_write(views_path, lambda f: np.save(f, graph.views))
    atomic_write(graph_path, lambda f: np.savez(f, **arrays))


def load_graph(kitchen: str, view_size: int = VIEW_SIZE, root: Path | None = None) -> StateGraph | None:
    """The cached graph, or None when there is none (or it is unreadable: then it gets rebuilt)."""
    graph_path, views_path = _cache_paths(kitchen, view_size, root or cache_dir())
    if not (graph_path.exists() and views_path.exists()):
        return None
    try:
        with np.load(graph_path) as z:
            a = {k: z[k] for k in z.files}
        views = np.load(views_path, mmap_mode="r")
        world = World(kitchen)
        ptr = a["vis_ptr"]
        visible = [
            Visibility(
                tuple(int(i) for i in a["vis_obj"][ptr[s] : ptr[s + 1]]),
                tuple(int(p) for p in a["vis_pixels"][ptr[s] : ptr[s + 1]]),
                world.objects[t].id if t >= 0 else None,
            )
            for s, t in enumerate(a["open_target"])
        ]
        graph = StateGraph(
            kitchen=kitchen,
            world=world,
            cells=[(int(x), int(z)) for x, z in a["cells"]],
            cell=a["cell"],
            heading=a["heading"],
            pitch=a["pitch"],
            opened=a["opened"],
            next_state=a["next"],
            ok=a["ok"],
            visible=visible,
            views=views,
        )
        if (
            views.shape != (graph.n_states, view_size, view_size, 3)
            or graph.next_state.shape[0] != graph.n_states
        ):
            raise ValueError(f"views {views.shape} do not match {graph.n_states} states")
        return graph
    except Exception as e:  # noqa: BLE001 - any unreadable cache file is rebuilt, not trusted
        print(
            f"kgnavbench: cached state graph of {kitchen} is unreadable ({e}); rebuilding it", file=sys.stderr
        )
        return None


def state_graph(kitchen: str, view_size: int = VIEW_SIZE, root: Path | None = None) -> StateGraph:
    """The state graph of a kitchen's start scene, from the cache or built (and cached) now."""
    check_name(kitchen)
    root = root or cache_dir()
    graph = load_graph(kitchen, view_size, root)
    if graph is None:
        try:  # fail before a minute of building, not after
            root.mkdir(parents=True, exist_ok=True)
            graph = build_state_graph(World(kitchen), view_size)
            save_graph(graph, root)
        except OSError as e:
            raise TaskError(
                f"cannot write the state-graph cache in {root} ({e.strerror or e}); "
                "set KGNAVBENCH_CACHE to a writable folder"
            ) from e
    return graph


def _build_one(job: tuple[str, int, str]) -> tuple[str, float, int]:
    kitchen, view_size, root = job
    start = time.perf_counter()
    graph = state_graph(kitchen, view_size, Path(root))
    return kitchen, time.perf_counter() - start, graph.n_states


def build_all(
    kitchens=KITCHEN_NAMES, view_size: int = VIEW_SIZE, root: Path | None = None, workers: int | None = None
):
    """Make sure every kitchen's graph is cached; one process per core. Yields (kitchen, s, states)."""
    root = root or cache_dir()
    jobs = [(k, view_size, str(root)) for k in kitchens]
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    if workers <= 1:
        yield from map(_build_one, jobs)
        return
    with ProcessPoolExecutor(workers) as pool:
        yield from pool.map(_build_one, jobs)


# ------------------------------------------------------------------------------------------------
# Shortest paths and experts


def bfs_distances(next_state: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """Fewest actions from every state to any goal state (-1: no path). Multi-source BFS on the reversed
    graph, one vectorised frontier step per distance level."""
    dist = np.full(len(next_state), -1, np.int64)
    frontier = np.asarray(goal, bool).copy()
    dist[frontier] = 0
    level = 0
    while frontier.any():
        level += 1
        frontier = frontier[next_state].any(axis=1) & (dist < 0)
        dist[frontier] = level
    return dist


def goal_mask(n_states: int, goal_states) -> np.ndarray:
    mask = np.zeros(n_states, bool)
    mask[list(goal_states)] = True
    return mask


def nearer_actions(dist: np.ndarray, dist_after: np.ndarray) -> np.ndarray:
    """(N, A) bool: the actions of states at BFS distance `dist` (N,) that lead one step nearer the goal
    (`dist_after` (N, A): the distance after each action); none on a goal or where it cannot be
    reached."""
    return (dist_after == (dist - 1)[:, None]) & (dist > 0)[:, None]


def optimal_action_mask(dist: np.ndarray, dist_after: np.ndarray) -> np.ndarray:
    """Every BFS-optimal action (N, 10): Stop on a goal state, else each action one step nearer."""
    optimal = nearer_actions(dist, dist_after)
    optimal[dist == 0, STOP] = True
    return optimal


def expert_actions(next_state: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The BFS-optimal action per state: Stop on a goal state, else the first action (paper order) whose
    next state is one step nearer; -1 where the goal cannot be reached."""
    nearer = nearer_actions(dist, dist[next_state])
    best = np.where(nearer.any(1), nearer.argmax(1), -1)
    best[dist == 0] = STOP
    return best


def shortest_trajectory(next_state: np.ndarray, dist: np.ndarray, start: int) -> list[int]:
    """BFS-optimal actions from start to the goal, ending with Stop."""
    if dist[start] < 0:
        raise TaskError(f"state {start} cannot reach the goal")
    best = expert_actions(next_state, dist)
    s, actions = start, []
    while dist[s] > 0:
        actions.append(int(best[s]))
        s = int(next_state[s, best[s]])
    return actions + [STOP]


def walk_back_trajectory(graph: StateGraph, destination: int, n_steps: int) -> tuple[int, list[int]]:
    """The paper's expert: walk n_steps back from the destination trying MoveBack, MoveLeft, RotateRight
    in that order (the first that succeeds is taken), then reverse the walk (MoveAhead, MoveRight,
    RotateLeft) so it ends at the destination; OpenObject first for an open destination, Stop last.
    Returns (start state, actions)."""
    opened = graph.opened[destination] >= 0
    s = graph.state_of(graph.pose(destination)) if opened else destination
    walk = []
    for _ in range(n_steps):
        for name in WALK_BACK_PRIORITY:
            a = ACTIONS.index(name)
            if graph.ok[s, a]:
                walk.append(name)
                s = int(graph.next_state[s, a])
                break
    actions = [ACTIONS.index(REVERSE[name]) for name in reversed(walk)]
    return s, actions + ([OPEN] if opened else []) + [STOP]


# ------------------------------------------------------------------------------------------------
# Targets


@dataclass(frozen=True)
class Target:
    """A target of a kitchen: found in its state graph (`find_targets`), and, once the task file is
    read (`load_tasks`), whether it is a training target and its fixed episodes' starts."""

    object_index: int
    object_id: str
    type: str
    kind: str  # "static" or "actionable"
    destination: int  # state index; its view is the target image
    goal_states: tuple[int, ...]  # every state where the target is visible
    seen: bool = False  # a training target (False: held out as an unseen target)
    starts: tuple[int, ...] = ()  # the fixed evaluation episodes' start states

    def goals(self, success_rule: str) -> tuple[int, ...]:
        """The states where Stop succeeds: 'destination' (the paper's rule) its destination only, the
        place its image shows; 'visible' (SAVN's) any state that shows it. The one place the success
        rules are spelled; the env, the trainer and the distances all ask here."""
        if success_rule == "destination":
            return (self.destination,)
        if success_rule == "visible":
            return self.goal_states
        raise TaskError(f"unknown success rule {success_rule!r}; choose one of {SUCCESS_RULES}")


def find_targets(graph: StateGraph) -> list[Target]:
    """Static and actionable targets of the kitchen's start scene, each with its destination."""
    world = graph.world
    start_hidden = [o.hidden for o in world.objects]
    seen_in: dict[int, list[int]] = {}
    for s, v in enumerate(graph.visible):
        for i in v.visible:
            seen_in.setdefault(i, []).append(s)
    targets = []
    for i, o in enumerate(world.objects):
        goal_states = seen_in.get(i, [])  # open or closed: wherever the target is in view
        if start_hidden[i]:
            kind = "actionable"  # visible only with its receptacle open
            candidates = goal_states
        elif o.pickupable or o.type in COMMON_ITEMS:
            kind = "static"  # its image shows it with nothing open
            candidates = [s for s in goal_states if graph.opened[s] < 0]
        else:
            continue
        if not candidates:
            continue
        destination = min(candidates, key=lambda s, i=i, o=o: _nearness(graph, s, i, o.center))
        targets.append(Target(i, o.id, o.type, kind, destination, tuple(goal_states)))
    return targets


def _nearness(graph: StateGraph, s: int, i: int, centre: tuple[float, float]) -> tuple:
    """Sort key of a goal state for object i: distance to the object, then more pixels, then index."""
    x, z = graph.cells[graph.cell[s]]
    d2 = (x * 0.25 - centre[0]) ** 2 + (z * 0.25 - centre[1]) ** 2
    v = graph.visible[s]
    return (round(d2, 6), -v.pixels[v.visible.index(i)], s)


# ------------------------------------------------------------------------------------------------
# Splits and fixed episodes (the task file)


def split_kitchens(actionable_counts: dict[str, int]) -> dict[str, list[str]]:
    """20 train (most actionable targets; ties: lower FloorPlan number), then val/test alternate."""
    order = sorted(actionable_counts, key=lambda k: (-actionable_counts[k], KITCHEN_NAMES.index(k)))
    rest = order[N_TRAIN_KITCHENS:]
    return {
        "train": sorted(order[:N_TRAIN_KITCHENS], key=KITCHEN_NAMES.index),
        "val": sorted(rest[0::2], key=KITCHEN_NAMES.index),
        "test": sorted(rest[1::2], key=KITCHEN_NAMES.index),
    }


def seen_targets(kitchen: str, targets: list[Target]) -> set[str]:
    """The paper's training targets of a training kitchen: every actionable target, then static targets
    by a shuffle seeded with the kitchen name until there are SEEN_TARGETS_PER_KITCHEN."""
    seen = {t.object_id for t in targets if t.kind == "actionable"}
    static = sorted(t.object_id for t in targets if t.kind == "static")
    random.Random(kitchen).shuffle(static)
    return seen | set(static[: max(0, SEEN_TARGETS_PER_KITCHEN - len(seen))])


def startable(graph: StateGraph) -> np.ndarray:
    """(S,) bool: the states an episode may start in, no receptacle open and at pitch 0."""
    return (np.arange(graph.n_states) < graph.n_closed) & (graph.pitch == START_PITCH)


def episode_starts(graph: StateGraph, target: Target, n: int = EPISODES_PER_TARGET) -> list[int]:
    """n closed states at pitch 0 that do not show the target, at least MIN_START_DISTANCE actions from
    the target's destination (the place its image shows), drawn (without replacement while there are
    enough) by a generator seeded with the target."""
    dist = bfs_distances(graph.next_state, goal_mask(graph.n_states, [target.destination]))
    unseen = ~goal_mask(graph.n_states, target.goal_states)  # the target is not in view at the start
    candidates = np.flatnonzero(startable(graph) & unseen & (dist >= MIN_START_DISTANCE))
    if len(candidates) == 0:
        return []
    digest = hashlib.sha256(f"{graph.kitchen}/{target.object_id}".encode()).digest()
    seed = int.from_bytes(digest[:8], "little")
    rng = np.random.default_rng(seed)
    picks = rng.choice(candidates, n, replace=len(candidates) < n)
    return [int(s) for s in picks]


def kitchen_task_record(graph: StateGraph, training: bool) -> dict:
    """One kitchen's entry of the task file: its targets, seen or not, and their fixed episodes. Only a
    training kitchen has seen targets; every target of a validation or test kitchen is unseen."""
    targets = find_targets(graph)
    seen = seen_targets(graph.kitchen, targets) if training else set()
    records, dropped = [], []
    for t in targets:
        starts = episode_starts(graph, t)
        if not starts:
            dropped.append(t.object_id)  # no state is 10 actions from its destination
            continue
        records.append(
            {
                "object": t.object_id,
                "type": t.type,
                "kind": t.kind,
                "seen": t.object_id in seen,
                "destination": t.destination,
                "starts": starts,
            }
        )
    return {
        "n_states": graph.n_states,
        "fingerprint": graph_fingerprint(graph.kitchen),
        "targets": records,
        "dropped": dropped,
    }


def build_task_file(kitchens=KITCHEN_NAMES, path: Path = TASKS_FILE, root: Path | None = None) -> dict:
    """Build (or load) every state graph, then write the splits, targets and fixed episodes."""
    for kitchen, seconds, n in build_all(kitchens, root=root):
        print(f"{kitchen:12s} {n:5d} states ({seconds:5.1f} s)", flush=True)
    graphs = {k: state_graph(k, root=root) for k in kitchens}
    counts = {k: sum(t.kind == "actionable" for t in find_targets(g)) for k, g in graphs.items()}
    splits = split_kitchens(counts) if len(kitchens) == len(KITCHEN_NAMES) else {"train": list(kitchens)}
    record = {
        "format": TASKS_FORMAT,
        "episodes_per_target": EPISODES_PER_TARGET,
        "min_start_distance": MIN_START_DISTANCE,
        "seen_targets_per_kitchen": SEEN_TARGETS_PER_KITCHEN,
        "splits": splits,
        "kitchens": {k: kitchen_task_record(g, k in splits["train"]) for k, g in graphs.items()},
    }
    text = json.dumps(record, separators=(",", ":"), sort_keys=True).encode()
    atomic_write(path, gzip.compress(text, mtime=0))
    load_task_file.cache_clear()
    return record


@cache
def load_task_file(path: Path = TASKS_FILE) -> dict:
    try:
        with gzip.open(path, "rt") as f:
            record = json.load(f)
        if record.get("format") != TASKS_FORMAT:
            raise ValueError(f"format {record.get('format')!r}, expected {TASKS_FORMAT}")
        for key in ("splits", "kitchens"):
            if not isinstance(record.get(key), dict):
                raise ValueError(f"no {key!r} table")
        return record
    except FileNotFoundError as e:
        raise TaskError(f"task file {path} is missing; run `make tasks` to build it") from e
    except (OSError, EOFError, json.JSONDecodeError, ValueError, AttributeError) as e:
        raise TaskError(f"task file {path} is corrupt ({type(e).__name__}: {e}); run `make tasks`") from e


def kitchen_split(kitchen: str) -> str:
    """'train', 'val' or 'test'."""
    check_name(kitchen)
    for split, names in load_task_file()["splits"].items():
        if kitchen in names:
            return split
    raise TaskError(f"{kitchen} is in no split of {TASKS_FILE}; run `make tasks`")


# ------------------------------------------------------------------------------------------------
# Everything an environment needs about one kitchen


@dataclass
class KitchenTasks:
    kitchen: str
    split: str  # train / val / test
    graph: StateGraph
    targets: list[Target]
    _dist: dict = field(default_factory=dict, repr=False)

    def target(self, object_id: str) -> Target:
        for t in self.targets:
            if t.object_id == object_id:
                return t
        raise TaskError(f"{object_id!r} is not a target of {self.kitchen}")

    def distances(self, target: Target, success_rule: str = "destination") -> np.ndarray:
        """BFS distance of every state to the target's goal states ('visible': any state that shows
        it; 'destination': the destination only). Computed once per target and rule."""
        goals = target.goals(success_rule)
        key = (target.object_id, success_rule)
        if key not in self._dist:
            self._dist[key] = bfs_distances(self.graph.next_state, goal_mask(self.graph.n_states, goals))
        return self._dist[key]

    def training_starts(self, target: Target) -> np.ndarray:
        """The states a training episode of the target may start from (the env's and the trainer's
        draws): closed, at pitch 0, the target not in view, at least MIN_START_DISTANCE actions from
        its destination; where no state is that far, the farthest such states. Computed once."""
        key = (target.object_id, "starts")
        if key not in self._dist:
            g = self.graph
            d = self.distances(target, "destination")
            ok = startable(g) & ~goal_mask(g.n_states, target.goal_states)
            far = np.flatnonzero(ok & (d >= MIN_START_DISTANCE))
            self._dist[key] = far if len(far) else np.flatnonzero(ok & (d == d[ok].max()))
        return self._dist[key]

    def curriculum_starts(self, target: Target) -> tuple[np.ndarray, np.ndarray]:
        """Start states for a curriculum on start distance, nearest first, and their BFS distances to
        the destination: the states with no receptacle open at pitch 0, as the training starts, but
        the target may be in view and the destination itself is one (where it is closed at pitch 0).
        Computed once."""
        key = (target.object_id, "curriculum")
        if key not in self._dist:
            d = self.distances(target, "destination")
            states = np.flatnonzero(startable(self.graph) & (d >= 0))
            states = states[np.argsort(d[states], kind="stable")]
            self._dist[key] = (states, d[states].astype(np.int64))
        return self._dist[key]


TARGET_FIELDS = {"object": str, "type": str, "kind": str, "seen": bool, "destination": int, "starts": list}


def check_task_entry(entry: dict) -> None:
    """A kitchen's entry of the task file has every field, each of its type (ValueError otherwise)."""
    if not isinstance(entry, dict) or not isinstance(entry.get("n_states"), int):
        raise ValueError("no n_states")
    if not isinstance(entry.get("targets"), list):
        raise ValueError("no targets list")
    for n, t in enumerate(entry["targets"]):
        if not isinstance(t, dict):
            raise ValueError(f"target {n} is not a record")
        for key, kind in TARGET_FIELDS.items():
            if key not in t:
                raise ValueError(f"target {n} has no {key!r}")
            if not isinstance(t[key], kind) or (kind is int and isinstance(t[key], bool)):
                raise ValueError(f"target {n}: {key}={t[key]!r} is not {kind.__name__}")
        if t["kind"] not in ("static", "actionable"):
            raise ValueError(f"target {n}: kind {t['kind']!r}")
        if not t["starts"] or not all(isinstance(s, int) and not isinstance(s, bool) for s in t["starts"]):
            raise ValueError(f"target {n}: starts must be state numbers")


def load_tasks(kitchen: str, view_size: int = VIEW_SIZE, root: Path | None = None) -> KitchenTasks:
    """The state graph (cached), with the targets, splits and fixed episodes of the task file."""
    record = load_task_file()
    check_name(kitchen)
    entry = record["kitchens"].get(kitchen)
    if entry is None:
        raise TaskError(f"{kitchen} is not in the task file {TASKS_FILE}; run `make tasks`")
    try:
        check_task_entry(entry)
    except (KeyError, TypeError, ValueError) as e:
        raise TaskError(f"the task file's entry for {kitchen} is malformed ({e}); run `make tasks`") from e
    graph = state_graph(kitchen, view_size, root)
    if entry["n_states"] != graph.n_states:
        raise TaskError(
            f"the task file was built for {entry['n_states']} states of {kitchen}, the state graph now has "
            f"{graph.n_states}; run `make tasks` to rebuild the episodes"
        )
    found = {t.object_id: t for t in find_targets(graph)}
    targets = []
    for t in entry["targets"]:
        f = found.get(t["object"])
        if f is None or f.destination != t["destination"] or f.kind != t["kind"]:
            raise TaskError(
                f"target {t['object']} of {kitchen} no longer matches the state graph; run `make tasks`"
            )
        starts = tuple(t["starts"])
        targets.append(dataclasses.replace(f, seen=t["seen"], starts=starts))
    return KitchenTasks(kitchen, kitchen_split(kitchen), graph, targets)


if __name__ == "__main__":
    import sys

    if len(sys.argv) > 1:
        sys.exit("usage: python -m kgnavbench.tasks  (builds all 30 kitchens; the splits need every one)")
    t0 = time.perf_counter()
    rec = build_task_file()
    n_targets = sum(len(r["targets"]) for r in rec["kitchens"].values())
    seconds = time.perf_counter() - t0
    print(f"wrote {TASKS_FILE}: {len(rec['kitchens'])} kitchens, {n_targets} targets in {seconds:.1f} s")
    for split, ks in rec["splits"].items():
        print(f"  {split:5s}: {', '.join(ks)}")
