"""Stage 3 — render: pseudo-egocentric (2.5D) views, the instance buffer and the top-down map.

How a view is made (`render_views`, batched over poses):
  1. Every edge of every ray-visible pymunk shape (object footprints, walls, doors) is taken into the
     camera frame and projected to a range of image columns — a scan-line rasteriser over the floor
     plan instead of one pymunk segment query per column; it yields exactly the hits a segment query
     through each column would, for all columns of all poses in a handful of array operations.
  2. Per (column, shape) the entry and exit depths give a vertical slice of the shape:
     [t_in, t_out] x [y_bottom, y_top]. Its image rows come from the pitch-aware projection; each pixel
     row is tested exactly against the slice, so a counter shows its top, an upper cabinet its
     underside, and a mug stands on the counter in front of the wall cabinets.
  3. A z-buffer (np.minimum.at over (pixel, hit) pairs) keeps the nearest surface per pixel; floor and
     ceiling fill the rest. Colours: per object type, face shading by the face's normal, lighter tops,
     darker undersides, fog with distance. The instance buffer (object index or -1) comes from the same
     z-buffer.

Depth is perpendicular to the image plane (column rays are F + u R), so walls stay straight.
Arrays start here: the world stage is plain Python and pymunk.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .world import (
    EYE_HEIGHT,
    FIELD_OF_VIEW,
    VISIBILITY_DISTANCE,
    Pose,
    World,
    heading_vector,
)

NEAR = 0.02
# An object is visible when it covers at least this many pixels of a VISIBILITY_SIZE instance buffer
# (ALFRED uses 10 px at 300x300; one size for visibility keeps the task independent of the view size).
VISIBILITY_SIZE = 128
MIN_VISIBLE_PIXELS = 6

# Colours are RGB. Types not listed get a stable colour from their name's hash.
TYPE_COLOURS = {
    "CounterTop": (196, 190, 180),
    "Cabinet": (150, 100, 60),
    "Drawer": (165, 115, 70),
    "Fridge": (225, 228, 232),
    "Microwave": (70, 70, 78),
    "StoveBurner": (40, 40, 40),
    "StoveKnob": (30, 30, 30),
    "Sink": (170, 175, 180),
    "SinkBasin": (140, 150, 160),
    "Faucet": (200, 200, 210),
    "Window": (150, 200, 235),
    "Shelf": (140, 95, 55),
    "ShelvingUnit": (120, 85, 50),
    "DiningTable": (130, 85, 45),
    "Chair": (110, 70, 40),
    "Stool": (90, 60, 35),
    "GarbageCan": (80, 110, 80),
    "Toaster": (190, 60, 50),
    "CoffeeMachine": (45, 45, 50),
    "Apple": (200, 30, 40),
    "Tomato": (230, 50, 30),
    "Egg": (245, 235, 210),
    "Lettuce": (100, 190, 60),
    "Potato": (170, 130, 80),
    "Bread": (210, 160, 90),
    "Mug": (60, 120, 200),
    "Cup": (90, 160, 220),
    "Bowl": (230, 200, 60),
    "Plate": (240, 240, 235),
    "Pot": (100, 100, 110),
    "Pan": (55, 55, 60),
    "Kettle": (180, 40, 120),
    "HousePlant": (40, 140, 60),
    "LightSwitch": (235, 235, 225),
}
WALL_COLOURS = ((214, 204, 184), (200, 196, 186), (222, 212, 196), (206, 200, 192))
FLOOR_COLOURS = ((150, 120, 92), (136, 108, 84))
CEILING_COLOUR = (232, 232, 228)
FLOOR_TILE = 0.5


def type_colour(object_type: str) -> tuple[int, int, int]:
    if object_type in TYPE_COLOURS:
        return TYPE_COLOURS[object_type]
    h = hashlib.md5(object_type.encode()).digest()
    hsv = np.array([[[h[0] % 180, 120 + h[1] % 110, 120 + h[2] % 120]]], np.uint8)
    return tuple(int(v) for v in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


@dataclass
class Geometry:
    """The ray-visible edges of a world in one state (which receptacle is open), as flat arrays."""

    p0: np.ndarray  # (E, 2) edge start (x, z)
    p1: np.ndarray  # (E, 2) edge end
    shade: np.ndarray  # (E,) face brightness from the edge normal
    group: np.ndarray  # (E,) shape index of the edge
    y0: np.ndarray  # (G,) bottom of each shape
    y1: np.ndarray  # (G,) top
    colour: np.ndarray  # (G, 3) float32 RGB
    instance: np.ndarray  # (G,) object index, -1 for walls
    is_wall: np.ndarray  # (G,) bool
    room_height: float


def build_geometry(world: World) -> Geometry:
    p0, p1, shade, group = [], [], [], []
    y0, y1, colour, instance = [], [], [], []
    light = np.array([0.6, 0.8])
    wall = 0
    for shape, info in world.solid_shapes():
        if info.object_index >= 0 and world.is_hidden(info.object_index):
            continue
        if hasattr(shape, "get_vertices"):
            verts = [(v.x, v.y) for v in shape.get_vertices()]
            edges = list(zip(verts, verts[1:] + verts[:1]))
        else:
            edges = [((shape.a.x, shape.a.y), (shape.b.x, shape.b.y))]
        g = len(y0)
        for a, b in edges:
            n = np.array([b[1] - a[1], a[0] - b[0]])
            n /= max(np.linalg.norm(n), 1e-9)
            p0.append(a)
            p1.append(b)
            shade.append(0.72 + 0.28 * abs(float(n @ light)))
            group.append(g)
        y0.append(info.y_range[0])
        y1.append(info.y_range[1])
        if info.kind == "wall":
            colour.append(WALL_COLOURS[wall % 4])
            wall += 1
        else:
            c = np.array(type_colour(world.objects[info.object_index].type), float)
            colour.append(c * (0.8 if info.kind == "shell" else 1.0))
        instance.append(info.object_index)
    return Geometry(
        p0=np.array(p0, np.float64),
        p1=np.array(p1, np.float64),
        shade=np.array(shade, np.float32),
        group=np.array(group, np.int64),
        y0=np.array(y0, np.float64),
        y1=np.array(y1, np.float64),
        colour=np.array(colour, np.float32),
        instance=np.array(instance, np.int32),
        is_wall=np.array(instance) < 0,
        room_height=world.kitchen.room_height,
    )


def geometry(world: World) -> Geometry:
    """Cached per world state: rebuilt only when a receptacle opens or closes."""
    key = (world.geometry_version, world.open_receptacle)
    cache = world.__dict__.setdefault("_render_geometry", {})
    if key not in cache:
        cache.clear()
        cache[key] = build_geometry(world)
    return cache[key]


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For counts [2, 0, 3]: owner [0, 0, 2, 2, 2] and offset [0, 1, 0, 1, 2]."""
    owner = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    offset = np.arange(len(owner)) - starts[owner]
    return owner, offset


@dataclass(frozen=True)
class _Cameras:
    """B pinhole cameras at the poses: position, forward and right vectors on the floor plane, pitch,
    the focal length in pixels and the image size."""

    origin: np.ndarray  # (B, 2)
    fwd: np.ndarray  # (B, 2)
    right: np.ndarray  # (B, 2)
    pitch: np.ndarray  # (B,) radians
    f: float
    W: int
    H: int

    @property
    def B(self) -> int:
        return len(self.origin)


def render_views(
    world: World, poses: list[Pose], width: int = 84, height: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Views (B, H, W, 3) uint8 RGB and instance buffers (B, H, W) int16 for the world's current state.

    A 2.5D ray caster in four passes over all poses at once: each wall and object edge into the image
    columns it crosses (`_edge_columns`), each column's entry and exit depth per shape with the walls
    set apart as background (`_shape_spans`), the pixel rows each span covers (`_span_pixels`), and the
    background of floor, ceiling and the nearest wall (`_background`); then the z-buffer and shading.
    """
    height = height or width
    geo = geometry(world)
    fwd = np.array([heading_vector(p.heading) for p in poses], np.float64)
    cam = _Cameras(
        origin=np.array([(p.x, p.z) for p in poses]),
        fwd=fwd,
        right=np.stack([fwd[:, 1], -fwd[:, 0]], 1),
        pitch=np.radians([p.pitch for p in poses]),
        f=(width / 2) / math.tan(math.radians(FIELD_OF_VIEW) / 2),
        W=width,
        H=height,
    )
    B, W, H = cam.B, width, height
    columns = _edge_columns(geo, cam)
    t_in, t_out, face, hit_grp, hit_col, walls = _shape_spans(geo, cam, *columns)
    hit, row, entry, pixel, inv = _span_pixels(geo, cam, t_in, t_out, hit_grp, hit_col)
    back_t, cid, light = _background(geo, cam, inv, *walls)
    hit_pose = hit_col // W

    zbuf = back_t.reshape(-1).copy()
    np.minimum.at(zbuf, pixel, entry)
    win = entry <= zbuf[pixel]
    hit, row, entry, pixel = hit[win], row[win], entry[win], pixel[win]

    # surfaces: the face hit first (shaded by its normal), else the top (lighter) or underside (darker)
    front = entry <= t_in[hit] + 1e-6
    top_or_bottom = np.where(inv[hit_pose[hit], row] > 0, np.float32(1.12), np.float32(0.62))
    shade = np.where(front, geo.shade[face[hit]], top_or_bottom)
    cid[pixel] = 3 + hit_grp[hit]
    light[pixel] = shade * (0.55 + 0.45 * np.exp(-0.22 * entry))
    table = np.concatenate([np.array([*FLOOR_COLOURS, CEILING_COLOUR], np.float32), geo.colour])
    image = np.take(table, cid, axis=0) * light[:, None]
    instance = np.take(np.r_[np.int16(-1), np.int16(-1), np.int16(-1), geo.instance.astype(np.int16)], cid)
    image = np.minimum(image, 255).astype(np.uint8).reshape(B, W, H, 3).transpose(0, 2, 1, 3)
    instance = instance.reshape(B, W, H).transpose(0, 2, 1)
    return np.ascontiguousarray(image), np.ascontiguousarray(instance)


def _edge_columns(geo, cam: _Cameras):
    """Every edge into camera coordinates (x to the right, z depth), clipped at the near plane, and
    its exact hit with each image column's ray it crosses: (pose, column, depth, edge, shape) per hit."""
    W, f = cam.W, cam.f
    rel0 = geo.p0[None] - cam.origin[:, None]  # (B, E, 2)
    rel1 = geo.p1[None] - cam.origin[:, None]
    xa = np.einsum("bek,bk->be", rel0, cam.right)
    za = np.einsum("bek,bk->be", rel0, cam.fwd)
    xb = np.einsum("bek,bk->be", rel1, cam.right)
    zb = np.einsum("bek,bk->be", rel1, cam.fwd)
    keep = (za > NEAR) | (zb > NEAR)
    b_idx, e_idx = np.nonzero(keep)
    xa, za, xb, zb = xa[keep], za[keep], xb[keep], zb[keep]
    # clip the behind-the-camera end to the near plane
    for xs, zs, xo, zo in ((xa, za, xb, zb), (xb, zb, xa, za)):
        behind = zs < NEAR
        s = (NEAR - zs[behind]) / (zo[behind] - zs[behind])
        xs[behind] = xs[behind] + s * (xo[behind] - xs[behind])
        zs[behind] = NEAR
    ca = W / 2 + f * xa / za
    cb = W / 2 + f * xb / zb
    c_lo = np.clip(np.ceil(np.minimum(ca, cb) - 0.5), 0, W).astype(np.int64)
    c_hi = np.clip(np.floor(np.maximum(ca, cb) - 0.5), -1, W - 1).astype(np.int64)
    counts = np.maximum(c_hi - c_lo + 1, 0)
    owner, offset = _expand(counts)
    col = c_lo[owner] + offset
    # exact hit of column ray x = u z with the edge
    u = (col + 0.5 - W / 2) / f
    dx, dz = xb[owner] - xa[owner], zb[owner] - za[owner]
    denom = dx - u * dz
    ok = np.abs(denom) > 1e-12
    s = np.where(ok, (u * za[owner] - xa[owner]) / np.where(ok, denom, 1.0), -1.0)
    t = za[owner] + s * dz
    ok &= (s >= -1e-9) & (s <= 1 + 1e-9) & (t > NEAR)
    owner, col, t = owner[ok], col[ok], t[ok]
    edge = e_idx[owner]
    return b_idx[owner], col, t, edge, geo.group[edge]


def _shape_spans(geo, cam: _Cameras, pose_of, col, t, edge, grp):
    """Per (pose, column, shape): its entry and exit depth and the face hit first. The walls enclose
    the room and span floor to ceiling, so each column's nearest wall hit is part of the dense
    background (with floor and ceiling) rather than a span to rasterise: returned apart, as each
    column's wall depth, colour index and shade."""
    B, W = cam.B, cam.W
    G = len(geo.y0)
    key = (pose_of * W + col) * G + grp
    order = np.argsort(key * 256.0 + np.minimum(t, 255.0))
    key, t, edge = key[order], t[order], edge[order]
    first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    last = np.r_[first[1:] - 1, len(key) - 1]
    hit_key = key[first]
    t_in, t_out, face = t[first], t[last], edge[first]
    hit_grp = hit_key % G
    hit_col = hit_key // G  # pose * W + column

    wall = geo.is_wall[hit_grp]
    wall_t = np.full(B * W, np.inf)
    np.minimum.at(wall_t, hit_col[wall], t_in[wall])
    wall_win = wall & (t_in <= wall_t[hit_col])
    wall_cid = np.zeros(B * W, np.int64)
    wall_shade = np.ones(B * W, np.float32)
    wall_cid[hit_col[wall_win]] = 3 + hit_grp[wall_win]
    wall_shade[hit_col[wall_win]] = geo.shade[face[wall_win]]
    keep = ~wall
    return t_in[keep], t_out[keep], face[keep], hit_grp[keep], hit_col[keep], (wall_t, wall_cid, wall_shade)


def _span_pixels(geo, cam: _Cameras, t_in, t_out, hit_grp, hit_col):
    """The pixel rows each shape's span covers, exactly: (span, row, entry depth, pixel) per covered
    pixel, and each pose's inverse ray slope per row (B, H)."""
    f, W, H = cam.f, cam.W, cam.H
    hit_pose = hit_col // W
    y_lo, y_hi = geo.y0[hit_grp], geo.y1[hit_grp]
    # rows spanned by the slice's corners. Pitch is a y-shear of the image (as 2.5D ray casters do):
    # row = H/2 + f ((eye - y) / t - tan(pitch)), so straight edges stay straight and verticals vertical.
    shift = np.tan(cam.pitch)[hit_pose]
    inv_in, inv_out = 1.0 / t_in, 1.0 / t_out
    corners = np.stack(
        [
            (EYE_HEIGHT - y_lo) * inv_in,
            (EYE_HEIGHT - y_hi) * inv_in,
            (EYE_HEIGHT - y_lo) * inv_out,
            (EYE_HEIGHT - y_hi) * inv_out,
        ]
    )
    corners = H / 2 - 0.5 + f * (corners - shift)
    r_lo = np.clip(np.ceil(corners.min(0)), 0, H).astype(np.int64)
    r_hi = np.clip(np.floor(corners.max(0)), -1, H - 1).astype(np.int64)
    counts = np.maximum(r_hi - r_lo + 1, 0)
    hit, offset = _expand(counts)
    row = r_lo[hit] + offset

    # exact coverage per (hit, row): slope (eye - y) / t of the ray through each pixel row, per pose
    tan_b = (np.arange(H) + 0.5 - H / 2)[None] / f + np.tan(cam.pitch)[:, None]  # (B, H)
    tan_b = np.where(np.abs(tan_b) < 1e-9, 1e-9, tan_b)
    inv = 1.0 / tan_b
    inv_p = inv[hit_pose[hit], row]
    a = (EYE_HEIGHT - y_hi[hit]) * inv_p
    b = (EYE_HEIGHT - y_lo[hit]) * inv_p
    entry = np.maximum(t_in[hit], np.minimum(a, b))
    covered = entry <= np.minimum(t_out[hit], np.maximum(a, b)) + 1e-9
    hit, row, entry = hit[covered], row[covered], entry[covered]
    pixel = hit_col[hit] * H + row  # (pose * W + column) * H + row
    return hit, row, entry, pixel, inv


def _background(geo, cam: _Cameras, inv, wall_t, wall_cid, wall_shade):
    """Per pixel, floor (tiled), ceiling or the column's wall, whichever is nearest: its depth
    (B, W, H), colour index and light (both flat, pixel = (pose * W + column) * H + row)."""
    B, W, f, origin, fwd, right = cam.B, cam.W, cam.f, cam.origin, cam.fwd, cam.right
    floor_t = np.where(inv > 0, EYE_HEIGHT * inv, np.inf)  # (B, H)
    ceil_t = np.where(inv < 0, (EYE_HEIGHT - geo.room_height) * inv, np.inf)
    wall_tc = wall_t.reshape(B, W, 1)
    back_t = np.minimum(np.minimum(floor_t, ceil_t)[:, None, :], wall_tc)  # (B, W, H)
    col_u = (np.arange(W) + 0.5 - W / 2) / f
    ray = fwd[:, None, :] + col_u[None, :, None] * right[:, None, :]  # (B, W, 2)
    floor_d = np.minimum(floor_t, 1e3).astype(np.float32)[:, None, :]  # (B, 1, H)
    fx = origin[:, 0, None, None].astype(np.float32) + floor_d * ray[:, :, 0, None].astype(np.float32)
    fz = origin[:, 1, None, None].astype(np.float32) + floor_d * ray[:, :, 1, None].astype(np.float32)
    tile = (np.floor(fx * (1 / FLOOR_TILE)) + np.floor(fz * (1 / FLOOR_TILE))).astype(np.int64) & 1
    cid = np.where(floor_t[:, None, :] <= ceil_t[:, None, :], tile, 2)
    is_wall = wall_tc <= back_t
    cid = np.where(is_wall, wall_cid.reshape(B, W, 1), cid).reshape(-1)
    light = np.where(is_wall, wall_shade.reshape(B, W, 1), np.float32(1.0))
    light = (light * (0.55 + 0.45 * np.exp(-0.22 * np.minimum(back_t, 50.0)))).astype(np.float32).reshape(-1)
    return back_t, cid, light


def render_view(world: World, pose: Pose | None = None, size: int = 84) -> np.ndarray:
    images, _ = render_views(world, [pose or world.pose], size)
    return images[0]


@dataclass(frozen=True)
class Visibility:
    visible: tuple[int, ...]  # object indices, sorted
    pixels: tuple[int, ...]  # instance-buffer pixels of each visible object (VISIBILITY_SIZE)
    open_target: str | None  # the openable receptacle OpenObject would open here


def visibility(world: World, poses: list[Pose], batch: int = 64) -> list[Visibility]:
    """Visibility per pose for the world's current state: an object is visible when it covers at least
    MIN_VISIBLE_PIXELS of a VISIBILITY_SIZE instance buffer, its footprint is within 1.5 m of the agent
    (pymunk point query) and it is not inside a closed receptacle. The open target is the visible
    openable whose pixels come nearest the image centre."""
    n_obj = len(world.objects)
    hidden = [world.is_hidden(i) for i in range(n_obj)]
    c = (VISIBILITY_SIZE - 1) / 2
    ys, xs = np.indices((VISIBILITY_SIZE, VISIBILITY_SIZE))
    centre_dist = ((ys - c) ** 2 + (xs - c) ** 2).reshape(-1)
    near_cache: dict[tuple[int, int], set[int]] = {}
    out = []
    for start in range(0, len(poses), batch):
        chunk = poses[start : start + batch]
        _, inst = render_views(world, chunk, VISIBILITY_SIZE)
        flat = inst.reshape(len(chunk), -1).astype(np.int64)
        for pose, ids in zip(chunk, flat):
            counts = np.bincount(ids + 1, minlength=n_obj + 1)[1:]
            if pose.cell not in near_cache:
                near_cache[pose.cell] = world.objects_within(pose, VISIBILITY_DISTANCE)
            visible = sorted(
                i for i in near_cache[pose.cell] if counts[i] >= MIN_VISIBLE_PIXELS and not hidden[i]
            )
            openables = [i for i in visible if world.objects[i].openable]
            target = None
            if openables:
                best = min(openables, key=lambda i: (float(centre_dist[ids == i].min()), i))
                target = world.objects[best].id
            out.append(Visibility(tuple(visible), tuple(int(counts[i]) for i in visible), target))
    return out


def visible_objects(world: World, pose: Pose | None = None) -> list[int]:
    """Indices of the objects visible from `pose` (default: the agent's), see `visibility`."""
    return list(visibility(world, [pose or world.pose])[0].visible)


def open_target(world: World, pose: Pose | None = None) -> str | None:
    """The visible openable receptacle nearest the image centre (what OpenObject opens), or None."""
    return visibility(world, [pose or world.pose])[0].open_target


def act(world: World, action: str):
    """One step of the world with OpenObject resolved from the current view."""
    target = None
    if action == "OpenObject":
        # an open receptacle closes first, so the target is chosen from the view as it will be then
        world.close()
        target = open_target(world)
    return world.step(action, target)


# ---------------------------------------------------------------------------------------------------
# top-down map


def top_down_map(
    world: World,
    size: int = 300,
    poses: list[Pose] | None = None,
    path: list[Pose] | None = None,
    highlight: list[int] | None = None,
) -> np.ndarray:
    """A bird's-eye map (RGB uint8): floor, reachable cells, objects by type, the agents and a path."""
    x0, z0, x1, z1 = world.kitchen.room
    margin = 0.2
    scale = (size - 1) / max(x1 - x0 + 2 * margin, z1 - z0 + 2 * margin)

    def px(x, z):  # image y grows downwards, world z grows "up" on the map
        return (int(round((x - x0 + margin) * scale)), int(round((z1 + margin - z) * scale)))

    img = np.full((size, size, 3), 40, np.uint8)
    cv2.rectangle(img, px(x0, z1), px(x1, z0), FLOOR_COLOURS[0], -1)
    cv2.rectangle(img, px(x0, z1), px(x1, z0), WALL_COLOURS[0], 2)
    g = world.kitchen.grid
    for x, z in world.kitchen.reachable_points:
        cv2.rectangle(
            img,
            px(x - g / 2 + 0.01, z + g / 2 - 0.01),
            px(x + g / 2 - 0.01, z - g / 2 + 0.01),
            FLOOR_COLOURS[1],
            -1,
        )
    order = sorted(range(len(world.objects)), key=lambda i: world.objects[i].y_range[1])
    for i in order:
        o = world.objects[i]
        if world.is_hidden(i):
            continue
        for shape in world.object_shapes[i]:
            # an open receptacle's closed box is out of the space (its shell and door are drawn below):
            # drawing it would hide what is inside, the Egg in the open Fridge
            if shape not in world.shape_info or shape.space is None:
                continue
            pts = np.array([px(v.x, v.y) for v in shape.get_vertices()], np.int32)
            cv2.fillConvexPoly(img, pts, type_colour(o.type), cv2.LINE_AA)
            edge = (255, 255, 0) if highlight and i in highlight else (20, 20, 20)
            cv2.polylines(img, [pts], True, edge, 1, cv2.LINE_AA)
    for shape, info in world.solid_shapes():
        if info.kind in ("shell", "door"):
            cv2.line(
                img,
                px(shape.a.x, shape.a.y),
                px(shape.b.x, shape.b.y),
                (255, 255, 255) if info.kind == "door" else (160, 160, 160),
                2,
                cv2.LINE_AA,
            )
    if path:
        pts = np.array([px(p.x, p.z) for p in path], np.int32)
        cv2.polylines(img, [pts], False, (255, 80, 200), 2, cv2.LINE_AA)
    for k, p in enumerate(poses if poses is not None else [world.pose]):
        fx, fz = heading_vector(p.heading)
        rx, rz = fz, -fx
        r, b = 0.15, 0.105  # nose and back corners of the agent's triangle, metres
        tri = [
            (p.x + fx * r, p.z + fz * r),
            (p.x - fx * b + rx * b, p.z - fz * b + rz * b),
            (p.x - fx * b - rx * b, p.z - fz * b - rz * b),
        ]
        colour = ((30, 120, 255), (255, 140, 0), (0, 200, 120), (220, 40, 40))[k % 4]
        cv2.fillConvexPoly(img, np.array([px(*q) for q in tri], np.int32), colour, cv2.LINE_AA)
    return img


def save_rgb(path, image: np.ndarray) -> None:
    """Write an RGB image with OpenCV (which expects BGR)."""
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
