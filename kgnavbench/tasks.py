"""Stage 4 — tasks: the discrete state graph of a kitchen, targets, destinations and shortest paths.

A state is (cell, heading, pitch, open receptacle or none) — DESIGN.md's finite set. Closed states
are every reachable cell x 4 headings x 4 pitches. OpenObject in a closed state opens the receptacle
that the view there picks (nearest the image centre), so each closed state has at most one open twin;
an open state behaves like its closed twin for every action but Stop (which keeps it open) and
OpenObject (which closes and reopens the same receptacle).

Targets (per kitchen, start scene):
  * static: an object of an eligible type (pickupable, or one of COMMON_ITEMS) that is visible from some
    closed state;
  * actionable: an object hidden inside a closed openable receptacle at the start, visible from some
    open state (its receptacle open).
Goal states of a target are the states where it is visible; its destination is the goal state nearest
the object (ties: more pixels, then the lowest state index), and its target image is the view there.

Shortest paths are multi-source BFS over the reversed transition table, one vectorised frontier
expansion per level (no Python loop per node).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .render import Visibility, visibility
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


@dataclass
class StateGraph:
    """Every state of one kitchen (start scene) with its transitions and what is visible there."""

    kitchen: str
    world: World
    cells: list[tuple[int, int]]
    cell: np.ndarray  # (S,) index into cells
    heading: np.ndarray  # (S,) degrees
    pitch: np.ndarray  # (S,) degrees
    opened: np.ndarray  # (S,) object index of the open receptacle, -1 for none
    next: np.ndarray  # (S, 10) next state per action (ACTIONS order)
    ok: np.ndarray  # (S, 10) whether the action succeeds (False: a collision or a failed action)
    visible: list[Visibility]  # (S,)

    @property
    def n_states(self) -> int:
        return len(self.cell)

    def pose(self, s: int) -> Pose:
        return Pose(self.cells[self.cell[s]], int(self.heading[s]), int(self.pitch[s]))

    def state_of(self, pose: Pose, opened: int = -1) -> int:
        closed = self._closed_index(
            self.cells.index(pose.cell), HEADINGS.index(pose.heading), PITCHES.index(pose.pitch)
        )
        if opened < 0:
            return closed
        s = int(self.next[closed, OPEN])
        if self.opened[s] != opened:
            raise ValueError(f"OpenObject at {pose} does not open object {opened}")
        return s

    @staticmethod
    def _closed_index(ci: int, hi: int, pi: int) -> int:
        return (ci * len(HEADINGS) + hi) * len(PITCHES) + pi

    def visible_mask(self, object_index: int) -> np.ndarray:
        return np.array([object_index in v.visible for v in self.visible])


def build_state_graph(world: World) -> StateGraph:
    """Enumerate the states, step the world for every (state, action) and record visibility."""
    world.close()
    cells = list(world.kitchen.reachable)
    closed = [Pose(c, h, p) for c in cells for h in HEADINGS for p in PITCHES]
    n_closed = len(closed)
    vis = visibility(world, closed)
    index = {pose: i for i, pose in enumerate(closed)}

    # open twins: one per closed state whose view has an openable receptacle to open
    twin = np.full(n_closed, -1, np.int64)
    open_states: list[tuple[int, int]] = []  # (closed state, receptacle index)
    for s, v in enumerate(vis):
        if v.open_target is not None:
            twin[s] = n_closed + len(open_states)
            open_states.append((s, world.index(v.open_target)))
    open_vis: list[Visibility | None] = [None] * len(open_states)
    by_receptacle: dict[int, list[int]] = {}
    for k, (_, r) in enumerate(open_states):
        by_receptacle.setdefault(r, []).append(k)
    for r, ks in by_receptacle.items():
        world.open(world.objects[r].id)
        for k, v in zip(ks, visibility(world, [closed[open_states[k][0]] for k in ks])):
            open_vis[k] = v
        world.close()

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
        next=nxt,
        ok=ok,
        visible=list(vis) + open_vis,
    )


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


@dataclass(frozen=True)
class Target:
    object_index: int
    object_id: str
    type: str
    kind: str  # "static" or "actionable"
    destination: int  # state index
    goal_states: tuple[int, ...]


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
        states = seen_in.get(i, [])
        if start_hidden[i]:
            kind = "actionable"
            states = [s for s in states if graph.opened[s] >= 0]
        elif o.pickupable or o.type in COMMON_ITEMS:
            kind = "static"
            states = [s for s in states if graph.opened[s] < 0]
        else:
            continue
        if not states:
            continue

        destination = min(states, key=lambda s, i=i, o=o: _nearness(graph, s, i, o.center))
        targets.append(Target(i, o.id, o.type, kind, destination, tuple(states)))
    return targets


def _nearness(graph: StateGraph, s: int, i: int, centre: tuple[float, float]) -> tuple:
    """Sort key of a goal state for object i: distance to the object, then more pixels, then index."""
    x, z = graph.cells[graph.cell[s]]
    d2 = (x * 0.25 - centre[0]) ** 2 + (z * 0.25 - centre[1]) ** 2
    v = graph.visible[s]
    return (round(d2, 6), -v.pixels[v.visible.index(i)], s)
