"""Stage 5 — tasks: targets, splits and fixed episodes in the state graphs of kgnavbench/graph.py.

Targets (per kitchen, AI2-THOR start scene):
  * static: an object of an eligible type — pickupable, or one of COMMON_ITEMS — visible from some
    closed state;
  * actionable: an object hidden inside a closed openable receptacle at the start, visible from some
    open state (its receptacle open).
Goal states of a target are the states where it is visible; its destination is the goal state nearest
the object (ties: more pixels, then the lowest state index), and its target image is the view there.

Splits (rules in code here, written down in docs/protocol.md):
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
"""

from __future__ import annotations

import dataclasses
import gzip
import hashlib
import json
import random
import sys
import time
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from .files import atomic_write
from .graph import (
    VIEW_SIZE,
    StateGraph,
    TaskError,
    bfs_distances,
    build_all,
    goal_mask,
    graph_fingerprint,
    state_graph,
)
from .kitchens import DATA_DIR, KITCHEN_NAMES, check_name

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
N_TRAIN_KITCHENS, N_VAL_KITCHENS = 20, 5
# see Target.goals and `outcome`: "destination" (the paper's words), "visible" (SAVN's), "arrival" (Zhu
# et al. 2017's: arriving at the destination ends the episode in success, Stop a no-op)
SUCCESS_RULES = ("visible", "destination", "arrival")
SEEN_TARGETS_PER_KITCHEN = 7  # the paper: 140 training targets in 20 training kitchens
EPISODES_PER_TARGET = 100
MIN_START_DISTANCE = 10
START_PITCH = 0
TASKS_FILE = DATA_DIR / "tasks.json.gz"
TASKS_FORMAT = 2  # 2: the paper's target split (7 seen per training kitchen, actionable first)


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
        if success_rule in ("destination", "arrival"):
            return (self.destination,)
        if success_rule == "visible":
            return self.goal_states
        raise TaskError(f"unknown success rule {success_rule!r}; choose one of {SUCCESS_RULES}")


def outcome(success_rule: str, stop, on_goal, stop_ends: bool):
    """Whether a step succeeds and whether it ends the episode, from whether its action was Stop and
    whether it leads onto a goal state of the rule (`Target.goals`): the one place success is decided
    (the env's step and the trainer's navigators both ask here; arrays or bools alike).
    'destination' and 'visible': success = Stop on a goal state; it ends the episode, and so does any
    Stop when `stop_ends` (else a Stop that fails is a no-op). 'arrival' (Zhu et al. 2017): success =
    arriving on the destination, whatever the action, and it ends the episode; Stop is a no-op
    (`stop_ends` must be False)."""
    if success_rule == "arrival":
        if stop_ends:
            raise TaskError("under the arrival rule Stop is a no-op: stop_ends must be False")
        return on_goal, on_goal
    if success_rule not in SUCCESS_RULES:
        raise TaskError(f"unknown success rule {success_rule!r}; choose one of {SUCCESS_RULES}")
    success = stop & on_goal
    return success, success | (stop & stop_ends)


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
    actionable = {t.object_id for t in targets if t.kind == "actionable"}
    static = sorted(t.object_id for t in targets if t.kind == "static")
    random.Random(kitchen).shuffle(static)
    return actionable | set(static[: max(0, SEEN_TARGETS_PER_KITCHEN - len(actionable))])


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
    training_ids = seen_targets(graph.kitchen, targets) if training else set()
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
                "seen": t.object_id in training_ids,
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
