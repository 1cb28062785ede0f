"""Stage 2 — world: one pymunk space per kitchen, the agent, doors, discrete moves and queries.

The floor is pymunk's plane (pymunk x = AI2-THOR x, pymunk y = AI2-THOR z). The space holds
  * OBJECT shapes: one static convex polygon per footprint piece of every object (fixtures and items);
  * WALL shapes: the four walls of the room;
  * NAV shapes: the border of the real reachable grid (ALFRED layout) — a segment on every cell edge
    between a reachable and an unreachable cell. A move is a segment query from the agent's cell to the
    next one against these, so collisions agree with the real grid by construction;
  * DOOR shapes: when a receptacle is open, its solid box is swapped for a hollow shell and a door
    swung open (drawers slide out instead), so rays reach what is inside;
  * the AGENT: a kinematic circle moved cell to cell.

Poses are discrete: a grid cell (ix, iz) (metres = index * 0.25), a heading in degrees (0 = +z,
90 = +x, as AI2-THOR's rotation y) and a camera pitch (-30, 0, 30, 60; positive looks down).

Plain Python and pymunk only (the card's "numpy-free" world stage).
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, replace

import pymunk

from .errors import KgnavbenchError
from .kitchens import Kitchen, KitchenError, KitchenObject, load_kitchen

ACTIONS = (
    "MoveAhead",
    "MoveBack",
    "MoveRight",
    "MoveLeft",
    "RotateRight",
    "RotateLeft",
    "LookUp",
    "LookDown",
    "OpenObject",
    "Stop",
)
HEADINGS = (0, 90, 180, 270)
PITCHES = (-30, 0, 30, 60)
EYE_HEIGHT = 1.576
FIELD_OF_VIEW = 90.0
VISIBILITY_DISTANCE = 1.5
AGENT_RADIUS = 0.2
DOOR_THICKNESS = 0.03

# shape categories (pymunk collision-filter bits)
OBJECT, WALL, NAV, DOOR, AGENT = 1, 2, 4, 8, 16
SOLID = OBJECT | WALL | DOOR  # what rays see


class WorldError(KgnavbenchError, ValueError):
    """Bad world input: unknown action, pose or object."""


@dataclass(frozen=True)
class Pose:
    cell: tuple[int, int]
    heading: int = 0
    pitch: int = 0

    @property
    def x(self) -> float:
        return self.cell[0] * 0.25

    @property
    def z(self) -> float:
        return self.cell[1] * 0.25

    def __str__(self) -> str:
        return f"{self.x:.2f},{self.z:.2f},{self.heading},{self.pitch}"


@dataclass(frozen=True)
class StepResult:
    action: str
    success: bool
    pose: Pose
    open_receptacle: str | None


@dataclass(frozen=True)
class ShapeInfo:
    """What a pymunk shape stands for; render reads it to draw the shape."""

    object_index: int  # index into World.objects; -1 for walls
    y_range: tuple[float, float]
    kind: str  # "solid", "shell", "door", "wall"


def heading_vector(heading: int) -> tuple[int, int]:
    """Unit grid step (dx, dz) of a heading: 0 -> +z, 90 -> +x, 180 -> -z, 270 -> -x."""
    return {0: (0, 1), 90: (1, 0), 180: (0, -1), 270: (-1, 0)}[heading % 360]


def move_offset(action: str, heading: int) -> tuple[int, int]:
    fx, fz = heading_vector(heading)
    rx, rz = fz, -fx  # right of forward: heading + 90
    return {
        "MoveAhead": (fx, fz),
        "MoveBack": (-fx, -fz),
        "MoveRight": (rx, rz),
        "MoveLeft": (-rx, -rz),
    }[action]


def parse_action(action: str) -> str:
    if action not in ACTIONS:
        raise WorldError(f"unknown action {action!r}: the actions are {', '.join(ACTIONS)}")
    return action


def _transform(points, dx: float, dz: float, dyaw_deg: float, pivot: tuple[float, float]):
    c, s = math.cos(math.radians(dyaw_deg)), math.sin(math.radians(dyaw_deg))
    px, pz = pivot
    out = []
    for x, z in points:
        x0, z0 = x - px, z - pz
        # AI2-THOR's yaw turns +z towards +x (clockwise seen from above)
        out.append((px + dx + c * x0 + s * z0, pz + dz - s * x0 + c * z0))
    return tuple(out)


class World:
    """A kitchen's pymunk space with the agent, its pose and the receptacle that is open (if any).

    `World(kitchen, seed=None)`: with a seed, movable objects take one of the kitchen's real
    alternative placements (ALFRED / rearrangement records) chosen by that seed; without one, the
    AI2-THOR start scene.
    """

    def __init__(self, kitchen: Kitchen | str, seed: int | None = None):
        self.kitchen = load_kitchen(kitchen) if isinstance(kitchen, str) else kitchen
        self.objects: list[KitchenObject] = list(self.kitchen.objects)
        self.seed = seed
        if seed is not None and self.kitchen.placements:
            self._apply_placement(random.Random(seed).choice(self.kitchen.placements))
        self.reachable = frozenset(self.kitchen.reachable)
        self.space = pymunk.Space()
        self.shape_info: dict[pymunk.Shape, ShapeInfo] = {}
        self.object_shapes: list[list[pymunk.Shape]] = [[] for _ in self.objects]
        self._door_shapes: list[pymunk.Shape] = []
        self.open_receptacle: str | None = None
        self.geometry_version = 0  # bumped whenever ray-visible shapes change; render caches on it
        self._build()
        self.pose = Pose(self.kitchen.reachable[0], 0, 0)

    # -- building -------------------------------------------------------------------------------------
    def _apply_placement(self, record) -> None:
        moved = {}
        for index, x, y, z, yaw in record:
            o = self.objects[index]
            dx, dy, dz = x - o.position[0], y - o.position[1], z - o.position[2]
            pivot = (o.position[0], o.position[2])
            moved[index] = replace(
                o,
                position=(x, y, z),
                center=_transform([o.center], dx, dz, yaw - o.yaw, pivot)[0],
                footprint=tuple(_transform(p, dx, dz, yaw - o.yaw, pivot) for p in o.footprint),
                y_range=(o.y_range[0] + dy, o.y_range[1] + dy),
                yaw=yaw,
            )
        self.objects = [moved.get(i, o) for i, o in enumerate(self.objects)]
        self._reparent(set(moved))

    def _reparent(self, moved: set[int]) -> None:
        """Moved objects get the smallest receptacle that holds their footprint centre at their height."""
        receptacles = [
            (i, o) for i, o in enumerate(self.objects) if o.receptacle and not o.pickupable and i not in moved
        ]
        parents: dict[int, str | None] = {}
        for i in moved:
            o = self.objects[i]
            best, best_area = None, math.inf
            for _, r in receptacles:
                if not (r.y_range[0] - 0.05 <= o.y_range[0] <= r.y_range[1] + 0.05):
                    continue
                for poly in r.footprint:
                    if _inside(o.center, poly):
                        area = _area(poly)
                        if area < best_area:
                            best, best_area = r.id, area
            parents[i] = best
        contents = {o.id: [c for c in o.contents] for o in self.objects}
        for i, parent in parents.items():
            oid = self.objects[i].id
            for c in contents.values():
                if oid in c:
                    c.remove(oid)
            if parent is not None:
                contents[parent].append(oid)
        self.objects = [
            replace(o, parent=parents.get(i, o.parent), contents=tuple(sorted(contents[o.id])))
            for i, o in enumerate(self.objects)
        ]
        self.objects = [replace(o, hidden=self._inside_closed(o, None)) for o in self.objects]

    def _inside_closed(self, o: KitchenObject, open_id: str | None) -> bool:
        seen = set()
        p = o.parent
        while p is not None and p not in seen:
            seen.add(p)
            parent = self.object(p)
            if parent.openable and parent.id != open_id:
                return True
            p = parent.parent
        return False

    def _add(self, shape: pymunk.Shape, category: int, info: ShapeInfo | None) -> pymunk.Shape:
        shape.filter = pymunk.ShapeFilter(categories=category)
        self.space.add(shape)
        if info is not None:
            self.shape_info[shape] = info
        return shape

    def _build(self) -> None:
        static = self.space.static_body
        for i, o in enumerate(self.objects):
            for poly in o.footprint:
                shape = pymunk.Poly(static, poly)
                self.object_shapes[i].append(self._add(shape, OBJECT, ShapeInfo(i, o.y_range, "solid")))
        x0, z0, x1, z1 = self.kitchen.room
        corners = [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]
        for a, b in zip(corners, corners[1:] + corners[:1]):
            wall = ShapeInfo(-1, (0.0, self.kitchen.room_height), "wall")
            self._add(pymunk.Segment(static, a, b, 0.0), WALL, wall)
        g = self.kitchen.grid
        for ix, iz in self.reachable:
            for dx, dz in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                if (ix + dx, iz + dz) in self.reachable:
                    continue
                mx, mz = (ix + dx / 2) * g, (iz + dz / 2) * g
                a = (mx - dz * g / 2, mz - dx * g / 2)
                b = (mx + dz * g / 2, mz + dx * g / 2)
                self._add(pymunk.Segment(static, a, b, 0.0), NAV, None)
        self.agent = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
        self.space.add(self.agent)
        self._add(pymunk.Circle(self.agent, AGENT_RADIUS), AGENT, None)

    # -- lookup ---------------------------------------------------------------------------------------
    def object(self, object_id: str) -> KitchenObject:
        return self.objects[self.index(object_id)]

    def index(self, object_id: str) -> int:
        """The object's index: the kitchen's (a placement moves objects, never reorders them)."""
        try:
            return self.kitchen.index(object_id)
        except KitchenError as e:
            raise WorldError(str(e)) from None

    def is_hidden(self, index: int) -> bool:
        """Inside a closed openable receptacle (given which one is open now)."""
        return self._inside_closed(self.objects[index], self.open_receptacle)

    # -- pose and moves -------------------------------------------------------------------------------
    def check_pose(self, pose: Pose) -> Pose:
        if pose.cell not in self.reachable:
            raise WorldError(f"({pose.x:.2f}, {pose.z:.2f}) is not a reachable cell of {self.kitchen.name}")
        if pose.heading not in HEADINGS:
            raise WorldError(f"heading {pose.heading} is not one of {HEADINGS}")
        if pose.pitch not in PITCHES:
            raise WorldError(f"pitch {pose.pitch} is not one of {PITCHES}")
        return pose

    def teleport(self, pose: Pose) -> None:
        self.pose = self.check_pose(pose)
        self.agent.position = (pose.x, pose.z)
        self.close()

    def can_move(self, cell: tuple[int, int], offset: tuple[int, int]) -> bool:
        """A segment query along the move against the reachable grid's border (pymunk)."""
        g = self.kitchen.grid
        a = (cell[0] * g, cell[1] * g)
        b = ((cell[0] + offset[0]) * g, (cell[1] + offset[1]) * g)
        return self.space.segment_query_first(a, b, 0.0, pymunk.ShapeFilter(mask=NAV)) is None

    def step(self, action: str, open_target: str | None = None) -> StepResult:
        """Apply one action. OpenObject opens `open_target` (chosen by render.open_target from the view);
        with no target it fails. An open receptacle closes before any action other than Stop."""
        parse_action(action)
        if action != "Stop":
            self.close()
        pose, success = self.pose, True
        if action in ("MoveAhead", "MoveBack", "MoveRight", "MoveLeft"):
            off = move_offset(action, pose.heading)
            success = self.can_move(pose.cell, off)
            if success:
                pose = replace(pose, cell=(pose.cell[0] + off[0], pose.cell[1] + off[1]))
        elif action in ("RotateRight", "RotateLeft"):
            pose = replace(pose, heading=(pose.heading + (90 if action == "RotateRight" else -90)) % 360)
        elif action in ("LookUp", "LookDown"):
            pitch = pose.pitch + (30 if action == "LookDown" else -30)
            success = pitch in PITCHES
            if success:
                pose = replace(pose, pitch=pitch)
        elif action == "OpenObject":
            success = open_target is not None
            if success:
                self.open(open_target)
        self.pose = pose
        self.agent.position = (pose.x, pose.z)
        return StepResult(action, success, pose, self.open_receptacle)

    # -- receptacles ----------------------------------------------------------------------------------
    def open(self, object_id: str) -> None:
        """Open a receptacle: its box becomes a hollow shell with the door swung out (drawers slide)."""
        index = self.index(object_id)
        o = self.objects[index]
        if not o.openable:
            raise WorldError(f"{object_id} is not openable")
        self.close()
        self.space.remove(*self.object_shapes[index])
        static = self.space.static_body
        for a, b, kind in door_segments(o):
            seg = pymunk.Segment(static, a, b, DOOR_THICKNESS / 2)
            self._door_shapes.append(self._add(seg, DOOR, ShapeInfo(index, o.y_range, kind)))
        self.open_receptacle = object_id
        self.geometry_version += 1

    def close(self) -> None:
        if self.open_receptacle is None:
            return
        index = self.index(self.open_receptacle)
        for s in self._door_shapes:
            self.shape_info.pop(s)
        self.space.remove(*self._door_shapes)
        self._door_shapes = []
        self.space.add(*self.object_shapes[index])
        self.open_receptacle = None
        self.geometry_version += 1

    # -- queries --------------------------------------------------------------------------------------
    def objects_within(self, pose: Pose, distance: float = VISIBILITY_DISTANCE) -> set[int]:
        """Indices of objects whose footprint comes within `distance` of the agent's axis (pymunk)."""
        hits = self.space.point_query((pose.x, pose.z), distance, pymunk.ShapeFilter(mask=OBJECT | DOOR))
        return {self.shape_info[h.shape].object_index for h in hits}

    def solid_shapes(self):
        """(shape, info) for everything rays can hit; render turns these into edges."""
        return [(s, self.shape_info[s]) for s in self.space.shapes if s.filter.categories & SOLID]


def door_segments(o: KitchenObject):
    """Thin walls of an open receptacle: back and sides of its box plus the door (or the slid drawer)."""
    poly = max(o.footprint, key=_area)
    fx, fz = o.front
    # the box in its own frame: u along the front normal, v across it
    us = [p[0] * fx + p[1] * fz for p in poly]
    vs = [p[0] * -fz + p[1] * fx for p in poly]
    u0, u1, v0, v1 = min(us), max(us), min(vs), max(vs)

    def world(u, v):
        return (u * fx - v * fz, u * fz + v * fx)

    depth, width = u1 - u0, v1 - v0
    if o.type == "Drawer":
        # slid out by most of its depth: a tray with an open top
        shift = 0.8 * depth
        a, b, c, d = u0 + shift, u1 + shift, v0, v1
        return [
            (world(a, c), world(a, d), "shell"),
            (world(a, c), world(b, c), "shell"),
            (world(a, d), world(b, d), "shell"),
            (world(b, c), world(b, d), "door"),
        ]
    segs = [
        (world(u0, v0), world(u0, v1), "shell"),  # back
        (world(u0, v0), world(u1, v0), "shell"),  # sides
        (world(u0, v1), world(u1, v1), "shell"),
    ]
    # the door hinges on the front edge at v1 and swings out to stand perpendicular to the front
    swing = min(width, 1.0)
    segs.append((world(u1, v1), world(u1 + swing, v1), "door"))
    return segs


def _area(poly) -> float:
    return abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(poly, poly[1:] + poly[:1]))) / 2


def _inside(p, poly) -> bool:
    """Point in convex polygon (either winding)."""
    sign = 0
    for a, b in zip(poly, poly[1:] + poly[:1]):
        c = (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
        if c != 0:
            if sign == 0:
                sign = 1 if c > 0 else -1
            elif (c > 0) != (sign > 0):
                return False
    return True


MAX_COORDINATE = 1000.0  # metres or degrees; a kitchen is a few metres across


def parse_pose(text: str, kitchen: Kitchen) -> Pose:
    """'x,z,heading,pitch' in metres and degrees (heading and pitch optional)."""
    try:
        parts = [float(v) for v in text.split(",")]
        if not 2 <= len(parts) <= 4:
            raise ValueError
    except ValueError:
        raise WorldError(f"bad pose {text!r}: expected x,z[,heading[,pitch]] like 0.25,-1.5,90,0") from None
    if not all(math.isfinite(v) for v in parts) or any(v != int(v) for v in parts[2:]):
        raise WorldError(f"bad pose {text!r}: x and z must be finite, heading and pitch whole degrees")
    if any(abs(v) > MAX_COORDINATE for v in parts):
        raise WorldError(f"bad pose {text!r}: numbers beyond {MAX_COORDINATE:g} lie outside any kitchen")
    g = kitchen.grid
    cell = (round(parts[0] / g), round(parts[1] / g))
    if abs(cell[0] * g - parts[0]) > 1e-6 or abs(cell[1] * g - parts[1]) > 1e-6:
        raise WorldError(f"bad pose {text!r}: x and z must lie on the {g} m grid")
    heading = int(parts[2]) if len(parts) > 2 else 0
    pitch = int(parts[3]) if len(parts) > 3 else 0
    return Pose(cell, heading, pitch)


__all__ = [
    "ACTIONS",
    "HEADINGS",
    "PITCHES",
    "EYE_HEIGHT",
    "FIELD_OF_VIEW",
    "VISIBILITY_DISTANCE",
    "KitchenError",
    "Pose",
    "StepResult",
    "World",
    "WorldError",
    "parse_action",
    "parse_pose",
]
