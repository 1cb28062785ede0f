"""Stage 1 — kitchens: the 30 real iTHOR kitchens (FloorPlan1..FloorPlan30) as compact package files.

`compile_kitchen(name, thor_data)` reads the public facts in ``../shared/thor_data`` (see its README and
our NOTICE) and returns a plain-dict record; `compile_all` writes them to
``kgnavbench/data/kitchens/FloorPlanN.json.gz``. `load_kitchen(name)` reads the committed file back into
frozen dataclasses. Only the compile step needs ``../shared``; nothing at run time does.

Units: metres, AI2-THOR's frame (x right, z forward, y up; the floor is the x-z plane). The reachable
grid is stored as integer cell indices ``(round(x / 0.25), round(z / 0.25))``.

Plain Python only (the world stage is "numpy-free"); numpy is imported lazily by the compiler to read
ALFRED's ``.npy`` layouts.
"""

from __future__ import annotations

import gzip
import json
import math
from dataclasses import dataclass
from functools import cache, lru_cache
from pathlib import Path

from .errors import KgnavbenchError
from .files import atomic_write

GRID = 0.25
KITCHEN_NAMES = tuple(f"FloorPlan{i}" for i in range(1, 31))
DATA_DIR = Path(__file__).parent / "data"
KITCHEN_DIR = DATA_DIR / "kitchens"
DEFAULT_THOR_DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "thor_data"
FORMAT_VERSION = 1

# Objects of these types never move, are never carried and are never re-placed.
OPENABLE_TYPES = ("Fridge", "Cabinet", "Microwave", "Drawer", "Safe", "Box")
# A reachable cell keeps a free square of this half-size around it: large fixtures whose boxes cover
# walkable floor (L-shaped counters; stools moved between AI2-THOR 2.1 and 5.0) are carved around it.
CARVE_HALF = 0.2
ROOM_HEIGHT = 2.6
DECIMALS = 3


class KitchenError(KgnavbenchError, ValueError):
    """Bad kitchen input: unknown name, missing or corrupt kitchen file."""


@dataclass(frozen=True)
class KitchenObject:
    id: str  # AI2-THOR objectId, "Type|+x.xx|+y.yy|+z.zz"
    type: str
    name: str  # AI2-THOR name ("Apple_3fef4551"); placements refer to it
    center: tuple[float, float]  # (x, z) of the bounding box
    position: tuple[float, float, float]  # AI2-THOR pivot (x, y, z); placements move it
    footprint: tuple[tuple[tuple[float, float], ...], ...]  # convex polygons (x, z), counter-clockwise
    y_range: tuple[float, float]  # bottom and top height above the floor
    yaw: float  # rotation about y, degrees
    openable: bool
    pickupable: bool
    receptacle: bool
    parent: str | None  # id of the receptacle holding it (None: on the floor / a fixture)
    contents: tuple[str, ...]
    hidden: bool  # inside a closed openable receptacle at the start
    front: tuple[float, float] | None  # openables: unit (x, z) vector pointing out of the door side


@dataclass(frozen=True)
class Kitchen:
    name: str
    grid: float
    reachable: tuple[tuple[int, int], ...]  # sorted cell indices
    room: tuple[float, float, float, float]  # xmin, zmin, xmax, zmax of the walls
    room_height: float
    objects: tuple[KitchenObject, ...]
    # Real alternative placements, each a whole-scene record: ((object index, x, y, z, yaw), ...)
    placements: tuple[tuple[tuple[int, float, float, float, float], ...], ...]

    def object(self, object_id: str) -> KitchenObject:
        return self.objects[self.index(object_id)]

    def index(self, object_id: str) -> int:
        for i, obj in enumerate(self.objects):
            if obj.id == object_id:
                return i
        raise KitchenError(f"kitchen {self.name} has no object {object_id!r}")

    @property
    def reachable_points(self) -> list[tuple[float, float]]:
        return [(ix * self.grid, iz * self.grid) for ix, iz in self.reachable]


def check_name(name: str) -> str:
    if name not in KITCHEN_NAMES:
        raise KitchenError(f"unknown kitchen {name!r}: the kitchens are FloorPlan1 .. FloorPlan30")
    return name


# ----------------------------------------------------------------------------------------------------
# Loading (run time)


@cache
def load_kitchen(name: str) -> Kitchen:
    check_name(name)
    path = KITCHEN_DIR / f"{name}.json.gz"
    try:
        with gzip.open(path, "rt") as f:
            record = json.load(f)
        return kitchen_from_record(record)
    except FileNotFoundError as e:
        raise KitchenError(f"kitchen file {path} is missing; run `make kitchens` to compile it") from e
    except (OSError, EOFError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise KitchenError(f"kitchen file {path} is corrupt ({type(e).__name__}: {e})") from e


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _points(v, dims: int) -> bool:
    return isinstance(v, list) and all(
        isinstance(p, list) and len(p) == dims and all(_is_number(c) for c in p) for p in v
    )


# field -> check of its value, for the record and for each object (a wrong type is a corrupt file)
_RECORD_FIELDS = {
    "name": lambda v: isinstance(v, str),
    "grid": _is_number,
    "reachable": lambda v: _points(v, 2) and all(isinstance(c, int) for p in v for c in p),
    "room": lambda v: isinstance(v, list) and len(v) == 4 and all(map(_is_number, v)),
    "room_height": _is_number,
    "objects": lambda v: isinstance(v, list) and all(isinstance(o, dict) for o in v),
    "placements": lambda v: isinstance(v, list) and all(isinstance(r, list) for r in v),
}
_OBJECT_FIELDS = {
    "id": lambda v: isinstance(v, str),
    "type": lambda v: isinstance(v, str),
    "name": lambda v: isinstance(v, str),
    "center": lambda v: isinstance(v, list) and len(v) == 2 and all(map(_is_number, v)),
    "position": lambda v: isinstance(v, list) and len(v) == 3 and all(map(_is_number, v)),
    "footprint": lambda v: isinstance(v, list) and all(_points(poly, 2) for poly in v),
    "y": lambda v: isinstance(v, list) and len(v) == 2 and all(map(_is_number, v)),
    "yaw": _is_number,
    "openable": lambda v: isinstance(v, bool),
    "pickupable": lambda v: isinstance(v, bool),
    "receptacle": lambda v: isinstance(v, bool),
    "parent": lambda v: v is None or isinstance(v, str),
    "contents": lambda v: isinstance(v, list) and all(isinstance(c, str) for c in v),
    "hidden": lambda v: isinstance(v, bool),
    "front": lambda v: v is None or (isinstance(v, list) and all(map(_is_number, v))),
}


def check_record(record: dict) -> None:
    """Every field of a kitchen record present and of its type; ValueError naming the first that is not."""
    for key, ok in _RECORD_FIELDS.items():
        if key not in record:
            raise ValueError(f"no {key!r}")
        if not ok(record[key]):
            raise ValueError(f"{key!r} has the wrong type or shape")
    for n, o in enumerate(record["objects"]):
        for key, ok in _OBJECT_FIELDS.items():
            if key not in o:
                raise ValueError(f"object {n} has no {key!r}")
            if not ok(o[key]):
                raise ValueError(
                    f"object {n} ({o.get('id')}): {key!r}={o[key]!r} has the wrong type or shape"
                )


def kitchen_from_record(record: dict) -> Kitchen:
    if not isinstance(record, dict):
        raise ValueError(f"a {type(record).__name__}, not a kitchen record")
    if record.get("format") != FORMAT_VERSION:
        raise ValueError(f"format {record.get('format')!r}, expected {FORMAT_VERSION}")
    check_record(record)
    objects = tuple(
        KitchenObject(
            id=o["id"],
            type=o["type"],
            name=o["name"],
            center=tuple(o["center"]),
            position=tuple(o["position"]),
            footprint=tuple(tuple(tuple(p) for p in poly) for poly in o["footprint"]),
            y_range=tuple(o["y"]),
            yaw=o["yaw"],
            openable=o["openable"],
            pickupable=o["pickupable"],
            receptacle=o["receptacle"],
            parent=o["parent"],
            contents=tuple(o["contents"]),
            hidden=o["hidden"],
            front=tuple(o["front"]) if o["front"] else None,
        )
        for o in record["objects"]
    )
    return Kitchen(
        name=record["name"],
        grid=record["grid"],
        reachable=tuple(tuple(c) for c in record["reachable"]),
        room=tuple(record["room"]),
        room_height=record["room_height"],
        objects=objects,
        placements=tuple(tuple(tuple(p) for p in rec) for rec in record["placements"]),
    )


@lru_cache(maxsize=1)
def object_types() -> tuple[str, ...]:
    """The 125 AI2-THOR object types, sorted: the vocabulary of visible-object vectors."""
    with open(DATA_DIR / "object_types.json") as f:
        return tuple(json.load(f))


def kitchen_summary(k: Kitchen) -> dict:
    return {
        "name": k.name,
        "reachable_cells": len(k.reachable),
        "objects": len(k.objects),
        "hidden_objects": sum(o.hidden for o in k.objects),
        "openable_receptacles": sum(o.openable for o in k.objects),
    }


# ----------------------------------------------------------------------------------------------------
# Compiling (needs ../shared/thor_data; run by `make kitchens` and by one test)


def _r(v: float) -> float:
    return round(float(v), DECIMALS)


def _convex_hull(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Andrew's monotone chain; counter-clockwise, no repeated end point."""
    pts = sorted(set(points))
    if len(pts) <= 2:
        return pts

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


def _inside_ccw(p: tuple[float, float], hull: list[tuple[float, float]]) -> bool:
    """Strictly inside a counter-clockwise convex polygon."""
    edges = zip(hull, hull[1:] + hull[:1], strict=True)
    return len(hull) > 2 and all(
        (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) > 0 for a, b in edges
    )


def _rect(x0: float, z0: float, x1: float, z1: float) -> list[list[float]]:
    return [[_r(x0), _r(z0)], [_r(x1), _r(z0)], [_r(x1), _r(z1)], [_r(x0), _r(z1)]]


def _carve(box: tuple[float, float, float, float], holes: list[tuple[float, float, float, float]]):
    """Axis-aligned box minus axis-aligned holes, as a list of disjoint rectangles (plain sweep)."""
    x0, z0, x1, z1 = box
    holes = [(max(a, x0), max(b, z0), min(c, x1), min(d, z1)) for a, b, c, d in holes]
    holes = [h for h in holes if h[0] < h[2] and h[1] < h[3]]
    if not holes:
        return [box]
    xs = sorted({x0, x1, *[h[0] for h in holes], *[h[2] for h in holes]})
    rects: list[tuple[float, float, float, float]] = []
    for xa, xb in zip(xs, xs[1:], strict=False):
        xm = (xa + xb) / 2
        zs = sorted([(h[1], h[3]) for h in holes if h[0] < xm < h[2]])
        z = z0
        for ha, hb in zs:
            if ha > z:
                rects.append((xa, z, xb, ha))
            z = max(z, hb)
        if z < z1:
            rects.append((xa, z, xb, z1))
    # merge vertically-equal neighbours along x to keep the polygon count small
    merged: list[list[float]] = []
    for r in sorted(rects, key=lambda r: (r[1], r[3], r[0])):
        if merged and merged[-1][1] == r[1] and merged[-1][3] == r[3] and abs(merged[-1][2] - r[0]) < 1e-9:
            merged[-1][2] = r[2]
        else:
            merged.append(list(r))
    return [tuple(m) for m in merged if m[2] - m[0] > 0.02 and m[3] - m[1] > 0.02]


def _footprint(meta: dict, reachable_pts: list[tuple[float, float]]):
    aabb = meta["axisAlignedBoundingBox"]
    c, s = aabb["center"], aabb["size"]
    box = (c["x"] - s["x"] / 2, c["z"] - s["z"] / 2, c["x"] + s["x"] / 2, c["z"] + s["z"] / 2)
    oob = meta.get("objectOrientedBoundingBox")
    if oob and oob.get("cornerPoints"):
        hull = _convex_hull([(p[0], p[2]) for p in oob["cornerPoints"]])
        covered = [p for p in reachable_pts if _inside_ccw(p, hull)]
        if meta["pickupable"] or not covered:
            # a rotated small object: its own hull; nothing to carve (pickupables stand on furniture)
            return [[[_r(x), _r(z)] for x, z in hull]]
        # movable furniture (stool, table) whose 5.0 box covers reachable 2.1.0 grid points: the grid is
        # authoritative, so its box is carved around those points
        reachable_pts = covered
    holes = [
        (x - CARVE_HALF, z - CARVE_HALF, x + CARVE_HALF, z + CARVE_HALF)
        for x, z in reachable_pts
        if box[0] - CARVE_HALF < x < box[2] + CARVE_HALF and box[1] - CARVE_HALF < z < box[3] + CARVE_HALF
    ]
    return [_rect(*r) for r in _carve(box, holes)]


def _front(meta: dict, pose: list | None, reachable_pts: list[tuple[float, float]]):
    """Unit axis vector from the object's centre to the side the agent opens it from."""
    c = meta["axisAlignedBoundingBox"]["center"]
    if pose is not None:
        tx, tz = pose[0], pose[1]
    else:  # no ALFRED pose for this id (2.1.0 vs 5.0 ids): the nearest reachable cell
        tx, tz = min(reachable_pts, key=lambda p: (p[0] - c["x"]) ** 2 + (p[1] - c["z"]) ** 2)
    yaw = math.radians(meta["rotation"]["y"])
    axes = [(math.cos(yaw), -math.sin(yaw)), (math.sin(yaw), math.cos(yaw))]
    axes += [(-a, -b) for a, b in axes]
    dx, dz = tx - c["x"], tz - c["z"]
    best = max(axes, key=lambda a: a[0] * dx + a[1] * dz)
    return [_r(best[0]), _r(best[1])]


@lru_cache(maxsize=4)
def _placement_sources(thor: Path) -> tuple[dict, ...]:
    """Scene name -> list of pose lists, from ALFRED's trajectories and the rearrangement episodes."""
    alfred: dict = {}
    with gzip.open(thor / "alfred/derived/kitchen_trajectory_scene_inits.json.gz", "rt") as f:
        for r in json.load(f):
            alfred.setdefault(r["floor_plan"], []).append(r["object_poses"])
    rearrange: dict = {}
    for year in (2021, 2022, 2023):
        path = thor / f"ai2thor-rearrangement/derived/{year}_combined_kitchens.json.gz"
        with gzip.open(path, "rt") as f:
            for scene, episodes in json.load(f).items():
                for ep in episodes:
                    rearrange.setdefault(scene, []).extend([ep["starting_poses"], ep["target_poses"]])
    return alfred, rearrange


def _placements(name: str, objects: list[dict], thor: Path) -> list[list[list[float]]]:
    """Whole-scene placement records from ALFRED and ai2thor-rearrangement.

    Rearrangement poses name AI2-THOR 5.0 objects exactly as our dump does. ALFRED's were recorded in
    AI2-THOR 2.1.0, whose object names carry other hashes, so its poses are matched by type: the k-th
    pose of a type (in name order) goes to the k-th object of that type (in name order).
    """
    by_name = {o["name"]: i for i, o in enumerate(objects) if o["pickupable"]}
    by_type: dict[str, list[int]] = {}
    for i, o in enumerate(objects):
        if o["pickupable"]:
            by_type.setdefault(o["type"], []).append(i)
    records: list[list[list[float]]] = []
    kept: set = set()  # the placements already recorded

    def add(poses: list[dict], match_by_type: bool):
        rec, used = [], set()
        if match_by_type:
            named = sorted({p["objectName"]: p for p in poses}.items())
            taken: dict[str, int] = {}
            pairs = []
            for pname, p in named:
                t = pname.rsplit("_", 1)[0]
                k = taken.get(t, 0)
                taken[t] = k + 1
                if k < len(by_type.get(t, [])):
                    pairs.append((by_type[t][k], p))
        else:
            pairs = [(by_name.get(p.get("objectName") or p.get("name")), p) for p in poses]
        for i, p in pairs:
            if i is None or i in used:
                continue
            used.add(i)
            pos, rot = p["position"], p["rotation"]
            rec.append([i, _r(pos["x"]), _r(pos["y"]), _r(pos["z"]), _r(rot["y"] % 360)])
        rec.sort()
        key = json.dumps(rec)
        if rec and key not in kept:
            kept.add(key)
            records.append(rec)

    alfred, rearrange = _placement_sources(thor)
    for poses in alfred.get(name, []):
        add(poses, match_by_type=True)
    for poses in rearrange.get(name, []):
        add(poses, match_by_type=False)
    return records


def compile_kitchen(name: str, thor_data: Path | str = DEFAULT_THOR_DATA) -> dict:
    import numpy as np  # only the compiler reads .npy files

    check_name(name)
    thor = Path(thor_data)
    if not (thor / "alfred").is_dir():
        raise KitchenError(f"{thor} is not the thor_data folder (no alfred/ in it)")
    layout = np.load(thor / f"alfred/gen/layouts/{name}-layout.npy")
    reachable = sorted({(round(float(x) / GRID), round(float(z) / GRID)) for x, z in layout})
    reachable_pts = [(ix * GRID, iz * GRID) for ix, iz in reachable]
    with open(thor / f"alfred/gen/layouts/{name}-openable.json") as f:
        open_poses = json.load(f)
    with open(thor / f"rl_ai2thor/objects_metadata/{name}_physics.json") as f:
        meta = json.load(f)

    floor = next(m for m in meta.values() if m["objectType"] == "Floor")
    fa = floor["axisAlignedBoundingBox"]
    room = [
        fa["center"]["x"] - fa["size"]["x"] / 2,
        fa["center"]["z"] - fa["size"]["z"] / 2,
        fa["center"]["x"] + fa["size"]["x"] / 2,
        fa["center"]["z"] + fa["size"]["z"] / 2,
    ]
    # the walls enclose every reachable cell and every object, whatever the Floor box says
    for m in meta.values():
        a = m["axisAlignedBoundingBox"]
        if m["objectType"] in ("Floor", "Window", "LightSwitch"):
            continue
        room[0] = min(room[0], a["center"]["x"] - a["size"]["x"] / 2)
        room[1] = min(room[1], a["center"]["z"] - a["size"]["z"] / 2)
        room[2] = max(room[2], a["center"]["x"] + a["size"]["x"] / 2)
        room[3] = max(room[3], a["center"]["z"] + a["size"]["z"] / 2)
    for x, z in reachable_pts:
        room = [min(room[0], x - 0.3), min(room[1], z - 0.3), max(room[2], x + 0.3), max(room[3], z + 0.3)]

    ids = {m["objectId"] for m in meta.values() if m["objectType"] != "Floor"}

    def parent_of(m: dict) -> str | None:
        parents = [p for p in (m.get("parentReceptacles") or []) if p in ids]
        if not m["pickupable"]:
            # fixtures stand on furniture, never in a pickupable or behind a door: AI2-THOR also lists
            # overlapping boxes (a Fridge "in" a Cabinet, a Cabinet "in" the Mug it holds)
            parents = [p for p in parents if not meta[p]["pickupable"] and not meta[p]["openable"]]
        return parents[0] if parents else None

    def hidden(m: dict) -> bool:
        visited = set()
        p = parent_of(m)
        while p is not None and p not in visited:
            visited.add(p)
            pm = meta[p]
            if pm["openable"] and not pm["isOpen"]:
                return True
            p = parent_of(pm)
        return False

    objects = []
    for oid in sorted(ids):
        m = meta[oid]
        a = m["axisAlignedBoundingBox"]
        y0 = a["center"]["y"] - a["size"]["y"] / 2
        y1 = a["center"]["y"] + a["size"]["y"] / 2
        if m["objectType"] == "CounterTop":
            y0 = y1 - 0.05  # AI2-THOR's counter slab is 1.6 cm thick: too thin to see at 84x84
        fp = _footprint(m, reachable_pts)
        if not fp:
            continue  # carved away entirely (a stool standing on a reachable cell)
        objects.append(
            {
                "id": oid,
                "type": m["objectType"],
                "name": m["name"],
                "center": [_r(a["center"]["x"]), _r(a["center"]["z"])],
                "position": [_r(m["position"][k]) for k in "xyz"],
                "footprint": fp,
                "y": [_r(max(0.0, y0)), _r(y1)],
                "yaw": _r(m["rotation"]["y"] % 360),
                "openable": bool(m["openable"]),
                "pickupable": bool(m["pickupable"]),
                "receptacle": bool(m["receptacle"]),
                "parent": parent_of(m),
                "contents": sorted(c for c in (m.get("receptacleObjectIds") or []) if c in ids),
                "hidden": hidden(m),
                "front": _front(m, open_poses.get(oid), reachable_pts) if m["openable"] else None,
            }
        )
    return {
        "format": FORMAT_VERSION,
        "name": name,
        "grid": GRID,
        "reachable": [list(c) for c in reachable],
        "room": [_r(v) for v in room],
        # a few windows and upper cabinets reach above 2.6 m: the ceiling sits above the tallest object
        "room_height": _r(max([ROOM_HEIGHT] + [o["y"][1] + 0.05 for o in objects])),
        "objects": objects,
        "placements": _placements(name, objects, thor),
    }


def compile_all(thor_data: Path | str = DEFAULT_THOR_DATA, out_dir: Path = KITCHEN_DIR) -> list[Path]:
    thor = Path(thor_data)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in KITCHEN_NAMES:
        record = compile_kitchen(name, thor)
        path = out_dir / f"{name}.json.gz"
        text = json.dumps(record, separators=(",", ":"), sort_keys=True).encode()
        atomic_write(path, gzip.compress(text, mtime=0))
        written.append(path)
    with open(thor / "rl_ai2thor/object_types_data.json") as f:
        types = sorted(json.load(f))
    atomic_write(out_dir.parent / "object_types.json", json.dumps(types, indent=0).encode())
    load_kitchen.cache_clear()
    return written


if __name__ == "__main__":
    import sys

    paths = compile_all(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_THOR_DATA)
    total = sum(p.stat().st_size for p in paths)
    print(f"compiled {len(paths)} kitchens into {KITCHEN_DIR} ({total / 1e6:.2f} MB)")
