"""Stage 4 — graph: the discrete state graph of a kitchen, its on-disk cache, shortest paths and the
experts.

A state is (cell, heading, pitch, open receptacle or none) — DESIGN.md's finite set. Closed states are
every reachable cell x 4 headings x 4 pitches, numbered ((cell * 4 + heading) * 4 + pitch). OpenObject
in a closed state opens the receptacle that the view there picks (nearest the image centre), so each
closed state has at most one open twin, numbered after all closed states. An open state behaves like
its closed twin for every action but Stop (which keeps it open) and OpenObject (which closes and
reopens the same receptacle): the auto-close rule. Transitions come from stepping the world itself;
each state also stores what is visible there and its 84x84 view, so an environment step is an array
lookup. Built once per kitchen and cached on disk (`cache_dir()`; `kgnavbench prepare` builds them all).

Shortest paths: multi-source BFS over the reversed transition table, one vectorised frontier
expansion per level (no Python loop per node). Experts: the BFS-optimal one (first action in the
paper's order that lowers the distance) and the paper's (walk back from the destination with
MoveBack / MoveLeft / RotateRight by priority, then reverse).

The next stage, kgnavbench/tasks.py, finds the targets in these graphs and fixes the episodes.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from . import render as render_module
from . import world as world_module
from .errors import KgnavbenchError
from .files import end_with_parent, require_checksum, write_with_checksum
from .kitchens import KITCHEN_DIR, KITCHEN_NAMES, check_name, object_types
from .render import Visibility, render_views, visibility
from .world import ACTIONS, HEADINGS, PITCHES, Pose, World

OPEN = ACTIONS.index("OpenObject")
STOP = ACTIONS.index("Stop")
MOVES = tuple(ACTIONS.index(a) for a in ("MoveAhead", "MoveBack", "MoveRight", "MoveLeft"))
VIEW_SIZE = 84
GRAPH_VERSION = 2  # bump when the states, transitions or views a kitchen's graph holds change
FINGERPRINTS_FILE = Path(__file__).parent / "data" / "graph_fingerprints.json"
# The paper's walk-back expert: from the destination try these in order, then reverse the walk.
WALK_BACK_PRIORITY = ("MoveBack", "MoveLeft", "RotateRight")
REVERSE = {"MoveBack": "MoveAhead", "MoveLeft": "MoveRight", "RotateRight": "RotateLeft"}


class TaskError(KgnavbenchError, ValueError):
    """Bad task input: unknown target, stale or corrupt task file, unreachable destination or state, an
    unwritable state-graph cache."""


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


def graph_parameters() -> dict:
    """The numbers a state graph is made with besides the kitchen file and the code: world.py's and
    render.py's module constants (grid moves, headings, pitches, eye height, field of view, visibility,
    colours, ...) and the view size. A change of one changes every fingerprint by itself."""
    values = {}
    for module in (world_module, render_module):
        for name, value in sorted(vars(module).items()):
            if name.isupper() and isinstance(value, (int, float, str, tuple, dict)):
                values[f"{module.__name__.rsplit('.', 1)[1]}.{name}"] = value
    values["graph.VIEW_SIZE"] = VIEW_SIZE
    return values


def graph_inputs_sha256(kitchen: str) -> str:
    """A hash of what decides a kitchen's state graph: GRAPH_VERSION (bumped when the code that makes
    states, transitions or views changes what it makes; tests/test_tasks.py holds a golden hash
    of FloorPlan1's graph that fails until it is bumped), the kitchen file and `graph_parameters`."""
    h = hashlib.sha256(f"graph-{GRAPH_VERSION}".encode())
    h.update((KITCHEN_DIR / f"{kitchen}.json.gz").read_bytes())
    h.update(json.dumps(graph_parameters(), sort_keys=True, default=repr).encode())
    return h.hexdigest()


@cache
def recorded_fingerprints() -> dict:
    """{kitchen: {"inputs": graph_inputs_sha256, "fingerprint": ...}}: the fingerprints of GRAPH_VERSION
    2, hashed (until 2026-12) from the bytes of world.py and render.py. They name the cached graphs,
    the task file stores them and every evaluation's identity hashes the task file: kept for the
    graphs they named, so that no saved evaluation is lost."""
    return json.loads(FINGERPRINTS_FILE.read_text())


@cache
def graph_fingerprint(kitchen: str) -> str:
    """Changes whenever what decides the kitchen's state graph does (`graph_inputs_sha256`): the
    recorded fingerprint while those inputs are the recorded ones, else the inputs' hash."""
    inputs = graph_inputs_sha256(kitchen)
    recorded = recorded_fingerprints().get(kitchen)
    if recorded is not None and recorded["inputs"] == inputs:
        return recorded["fingerprint"]
    return inputs[:16]


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
    write_with_checksum(views_path, lambda f: np.save(f, graph.views))
    write_with_checksum(graph_path, lambda f: np.savez(f, **arrays))


def _check_graph_arrays(a: dict, n_objects: int) -> None:
    """Raise ValueError where the arrays of a cached graph cannot be a state graph (a transition or an
    object out of range, a length that disagrees): a file that matches its checksum is what was
    written, and this says that what was written makes sense."""
    n = len(a["cell"])
    for name in ("heading", "pitch", "opened", "open_target"):
        if a[name].shape != (n,):
            raise ValueError(f"{name} has shape {a[name].shape}, not ({n},)")
    for name in ("next", "ok"):
        if a[name].shape != (n, len(ACTIONS)):
            raise ValueError(f"{name} has shape {a[name].shape}, not ({n}, {len(ACTIONS)})")
    ranges = {
        "next": (a["next"], 0, n),
        "cell": (a["cell"], 0, len(a["cells"])),
        "opened": (a["opened"], -1, n_objects),
        "open_target": (a["open_target"], -1, n_objects),
        "vis_obj": (a["vis_obj"], 0, n_objects),
    }
    for name, (values, low, high) in ranges.items():
        if values.size and (values.min() < low or values.max() >= high):
            raise ValueError(f"{name} points outside {low}..{high - 1}")
    ptr = a["vis_ptr"]
    if ptr.shape != (n + 1,) or ptr[0] != 0 or (np.diff(ptr) < 0).any() or ptr[-1] != len(a["vis_obj"]):
        raise ValueError("its visibility index does not cover its visible objects")
    if a["vis_pixels"].shape != a["vis_obj"].shape:
        raise ValueError("visible objects and their pixel counts differ in number")


def load_graph(kitchen: str, view_size: int = VIEW_SIZE, root: Path | None = None) -> StateGraph | None:
    """The cached graph, or None when there is none, or when it is unreadable, has no checksum or does not
    match it, or makes no sense as a graph: then it gets rebuilt, never trusted."""
    graph_path, views_path = _cache_paths(kitchen, view_size, root or cache_dir())
    if not (graph_path.exists() and views_path.exists()):
        return None
    try:
        require_checksum(graph_path)
        require_checksum(views_path)
        with np.load(graph_path) as z:
            a = {k: z[k] for k in z.files}
        views = np.load(views_path, mmap_mode="r")
        world = World(kitchen)
        _check_graph_arrays(a, len(world.objects))
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
            f"kgnavbench: cached state graph of {kitchen} cannot be trusted ({e}); rebuilding it",
            file=sys.stderr,
        )
        return None


def is_cached(kitchen: str, view_size: int = VIEW_SIZE, root: Path | None = None) -> bool:
    """Whether the kitchen's state graph and views are in the cache (a first use builds them: seconds
    to a minute)."""
    return all(path.is_file() for path in _cache_paths(kitchen, view_size, root or cache_dir()))


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
    with ProcessPoolExecutor(workers, initializer=end_with_parent, initargs=(os.getpid(),)) as pool:
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
