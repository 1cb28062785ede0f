"""Stage 2 — world: pymunk space per kitchen, moves on the real grid, doors, seeded placements, bad input."""

from __future__ import annotations

import math

import pymunk
import pytest

from kgnavbench import render
from kgnavbench import world as world_module
from kgnavbench.kitchens import KITCHEN_NAMES, KitchenError
from kgnavbench.world import ACTIONS, Pose, World, WorldError, parse_action, parse_pose

EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"
# In FloorPlan1 at (-1.00, 1.00), facing -x and looking down 30 degrees, the closed fridge fills the view.
FACING_FRIDGE = Pose((-4, 4), 270, 30)
OFFSETS = ((1, 0), (-1, 0), (0, 1), (0, -1))
CENTRE = (-4, -6)  # a FloorPlan1 cell whose four neighbours are all reachable
EDGE = (-5, -7)  # a FloorPlan1 corner cell: (-6, -7) and (-5, -8) are not reachable


@pytest.fixture
def fp1() -> World:
    return World("FloorPlan1")


def _area(poly) -> float:
    return abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(poly, poly[1:] + poly[:1]))) / 2


# ---------------------------------------------------------------------------------------------------
# collisions agree with the real grid, and the pymunk geometry agrees with it too


@pytest.mark.parametrize("name", KITCHEN_NAMES)
def test_moves_and_geometry_agree_with_the_reachable_grid(name):
    w = World(name)
    objects_only = pymunk.ShapeFilter(mask=world_module.OBJECT)
    assert w.reachable == frozenset(w.kitchen.reachable)
    for cell in w.kitchen.reachable:
        for off in OFFSETS:
            neighbour = (cell[0] + off[0], cell[1] + off[1])
            assert w.can_move(cell, off) == (neighbour in w.reachable), (name, cell, off)
        # standing at the cell's centre overlaps no object that stands on the floor
        x, z = cell[0] * 0.25, cell[1] * 0.25
        hits = w.space.point_query((x, z), 0.0, objects_only)
        on_floor = [
            w.objects[w.shape_info[h.shape].object_index].id
            for h in hits
            if w.objects[w.shape_info[h.shape].object_index].y_range[0] < 0.3
        ]
        assert not on_floor, f"{name}: the agent at ({x:.2f}, {z:.2f}) stands inside {on_floor}"
        # and every cell lies inside the walls, with the agent's body clear of them
        walls = w.space.point_query(
            (x, z), world_module.AGENT_RADIUS, pymunk.ShapeFilter(mask=world_module.WALL)
        )
        assert not walls, (name, cell)


def test_every_move_from_every_cell_matches_the_grid(fp1):
    """Walk the whole state graph of FloorPlan1 with step(): success iff the target cell is reachable."""
    expected = {
        0: {"MoveAhead": (0, 1), "MoveBack": (0, -1), "MoveRight": (1, 0), "MoveLeft": (-1, 0)},
        90: {"MoveAhead": (1, 0), "MoveBack": (-1, 0), "MoveRight": (0, -1), "MoveLeft": (0, 1)},
        180: {"MoveAhead": (0, -1), "MoveBack": (0, 1), "MoveRight": (-1, 0), "MoveLeft": (1, 0)},
        270: {"MoveAhead": (-1, 0), "MoveBack": (1, 0), "MoveRight": (0, 1), "MoveLeft": (0, -1)},
    }
    collisions = 0
    for cell in fp1.kitchen.reachable:
        for heading, moves in expected.items():
            for action, (dx, dz) in moves.items():
                start = Pose(cell, heading, 30)
                fp1.teleport(start)
                r = fp1.step(action)
                target = (cell[0] + dx, cell[1] + dz)
                assert r.success == (target in fp1.reachable)
                assert r.pose == fp1.pose
                assert fp1.pose == (Pose(target, heading, 30) if r.success else start)
                assert tuple(fp1.agent.position) == pytest.approx((fp1.pose.x, fp1.pose.z))
                collisions += not r.success
    assert collisions > 0


def test_moves_per_heading(fp1):
    # heading 0 looks along +z, 90 along +x; right of heading 0 is +x
    cases = [
        (0, "MoveAhead", (0, 1)),
        (0, "MoveBack", (0, -1)),
        (0, "MoveRight", (1, 0)),
        (0, "MoveLeft", (-1, 0)),
        (90, "MoveAhead", (1, 0)),
        (90, "MoveRight", (0, -1)),
        (180, "MoveAhead", (0, -1)),
        (180, "MoveRight", (-1, 0)),
        (270, "MoveAhead", (-1, 0)),
        (270, "MoveRight", (0, 1)),
        (270, "MoveLeft", (0, -1)),
        (270, "MoveBack", (1, 0)),
    ]
    for heading, action, (dx, dz) in cases:
        fp1.teleport(Pose(CENTRE, heading, 0))
        r = fp1.step(action)
        assert r.success, (heading, action)
        assert r.pose == Pose((CENTRE[0] + dx, CENTRE[1] + dz), heading, 0), (heading, action)
        # metres follow the cell: 0.25 m per step
        assert (r.pose.x, r.pose.z) == pytest.approx(((CENTRE[0] + dx) * 0.25, (CENTRE[1] + dz) * 0.25))


@pytest.mark.parametrize(
    "heading, action",
    [(270, "MoveAhead"), (180, "MoveAhead"), (90, "MoveBack"), (0, "MoveBack"), (0, "MoveLeft")],
)
def test_move_into_an_unreachable_cell_fails_and_keeps_the_pose(fp1, heading, action):
    start = Pose(EDGE, heading, -30)
    fp1.teleport(start)
    r = fp1.step(action)
    assert not r.success
    assert r.pose == start and fp1.pose == start
    assert tuple(fp1.agent.position) == pytest.approx((EDGE[0] * 0.25, EDGE[1] * 0.25))


def test_rotations_cycle_headings(fp1):
    fp1.teleport(Pose(CENTRE, 0, 0))
    seen = [fp1.step("RotateRight").pose.heading for _ in range(4)]
    assert seen == [90, 180, 270, 0]
    seen = [fp1.step("RotateLeft").pose.heading for _ in range(4)]
    assert seen == [270, 180, 90, 0]
    assert fp1.pose.cell == CENTRE and fp1.pose.pitch == 0


def test_pitch_steps_and_limits(fp1):
    fp1.teleport(Pose(CENTRE, 90, 0))
    assert fp1.step("LookUp").pose.pitch == -30
    r = fp1.step("LookUp")
    assert not r.success and r.pose.pitch == -30
    pitches = [fp1.step("LookDown").pose.pitch for _ in range(3)]
    assert pitches == [0, 30, 60]
    r = fp1.step("LookDown")
    assert not r.success and r.pose == Pose(CENTRE, 90, 60)


def test_stop_and_rotations_always_succeed(fp1):
    fp1.teleport(Pose(EDGE, 0, 0))
    for action in ("Stop", "RotateRight", "RotateLeft", "Stop"):
        assert fp1.step(action).success
    assert fp1.pose == Pose(EDGE, 0, 0)


# ---------------------------------------------------------------------------------------------------
# receptacles


def test_open_object_without_a_target_fails(fp1):
    fp1.teleport(Pose(CENTRE, 0, 0))
    r = fp1.step("OpenObject")
    assert not r.success and r.open_receptacle is None and fp1.pose == Pose(CENTRE, 0, 0)


def test_open_object_with_nothing_openable_in_view_fails(fp1):
    # the middle of the room looking along +z at pitch -30: nothing openable within 1.5 m in view
    fp1.teleport(Pose((-1, -6), 0, -30))
    assert render.open_target(fp1) is None
    r = render.act(fp1, "OpenObject")
    assert not r.success and fp1.open_receptacle is None


@pytest.mark.parametrize("action", [a for a in ACTIONS if a != "Stop"])
def test_open_receptacle_closes_before_any_other_action(fp1, action):
    fp1.teleport(FACING_FRIDGE)
    fp1.open(FRIDGE)
    egg = fp1.index(EGG)
    assert fp1.open_receptacle == FRIDGE and not fp1.is_hidden(egg)
    r = fp1.step(action)
    assert r.open_receptacle is None and fp1.open_receptacle is None
    assert fp1.is_hidden(egg)


def test_stop_keeps_the_receptacle_open(fp1):
    fp1.teleport(FACING_FRIDGE)
    fp1.open(FRIDGE)
    r = fp1.step("Stop")
    assert r.success and r.open_receptacle == FRIDGE and fp1.open_receptacle == FRIDGE
    assert not fp1.is_hidden(fp1.index(EGG))


def test_teleport_closes_the_open_receptacle(fp1):
    fp1.open(FRIDGE)
    fp1.teleport(FACING_FRIDGE)
    assert fp1.open_receptacle is None


def test_opening_the_fridge_reveals_the_egg_and_closing_hides_it(fp1):
    egg, fridge = fp1.index(EGG), fp1.index(FRIDGE)
    fp1.teleport(FACING_FRIDGE)
    assert fp1.is_hidden(egg)
    assert fridge in render.visible_objects(fp1) and egg not in render.visible_objects(fp1)
    assert render.open_target(fp1) == FRIDGE

    r = render.act(fp1, "OpenObject")
    assert r.success and r.open_receptacle == FRIDGE and r.pose == FACING_FRIDGE
    assert not fp1.is_hidden(egg)
    visible = render.visible_objects(fp1)
    assert egg in visible and fridge in visible

    r = fp1.step("RotateRight")  # any action but Stop closes it
    fp1.step("RotateLeft")
    assert fp1.open_receptacle is None and fp1.pose == FACING_FRIDGE
    assert fp1.is_hidden(egg)
    assert egg not in render.visible_objects(fp1)


def test_open_fridge_is_a_hollow_shell_with_a_door(fp1):
    fridge = fp1.index(FRIDGE)
    centre = fp1.objects[fridge].center
    solid = pymunk.ShapeFilter(mask=world_module.OBJECT)
    inside = [fp1.shape_info[h.shape].object_index for h in fp1.space.point_query(centre, 0.0, solid)]
    assert fridge in inside
    shapes_before = len(fp1.space.shapes)
    version = fp1.geometry_version

    fp1.open(FRIDGE)
    inside = [fp1.shape_info[h.shape].object_index for h in fp1.space.point_query(centre, 0.0, solid)]
    assert fridge not in inside  # the box is gone: rays reach the Egg
    doors = [(s, i) for s, i in fp1.solid_shapes() if i.object_index == fridge]
    assert {i.kind for _, i in doors} == {"shell", "door"}
    assert fp1.geometry_version > version
    # the fridge is still near the agent (its shell counts for the visibility distance)
    assert fridge in fp1.objects_within(FACING_FRIDGE)

    fp1.close()
    inside = [fp1.shape_info[h.shape].object_index for h in fp1.space.point_query(centre, 0.0, solid)]
    assert fridge in inside
    assert len(fp1.space.shapes) == shapes_before
    assert all(i.kind in ("solid", "wall") for _, i in fp1.solid_shapes())


def test_only_openable_objects_open(fp1):
    with pytest.raises(WorldError, match="not openable"):
        fp1.open(EGG)
    assert fp1.open_receptacle is None


def test_objects_within_measures_from_the_agent_to_the_footprint(fp1):
    pose = Pose((-5, -3), 0, 0)
    near = fp1.objects_within(pose, 1.5)
    for i, o in enumerate(fp1.objects):
        d = min(_distance_to_polygon((pose.x, pose.z), poly) for poly in o.footprint)
        if abs(d - 1.5) > 1e-3:
            assert (i in near) == (d < 1.5), (o.id, d)


def _distance_to_polygon(p, poly) -> float:
    """Plain-geometry distance from a point to a convex polygon (0 inside)."""
    px, pz = p
    inside = all(
        (b[0] - a[0]) * (pz - a[1]) - (b[1] - a[1]) * (px - a[0]) >= 0
        for a, b in zip(poly, poly[1:] + poly[:1])
    ) or all(
        (b[0] - a[0]) * (pz - a[1]) - (b[1] - a[1]) * (px - a[0]) <= 0
        for a, b in zip(poly, poly[1:] + poly[:1])
    )
    if inside:
        return 0.0
    best = math.inf
    for a, b in zip(poly, poly[1:] + poly[:1]):
        ax, az, bx, bz = a[0], a[1], b[0], b[1]
        L = (bx - ax) ** 2 + (bz - az) ** 2
        t = 0.0 if L == 0 else max(0.0, min(1.0, ((px - ax) * (bx - ax) + (pz - az) * (bz - az)) / L))
        best = min(best, math.hypot(px - ax - t * (bx - ax), pz - az - t * (bz - az)))
    return best


# ---------------------------------------------------------------------------------------------------
# seeded placements


def test_same_seed_same_objects_different_seeds_move_objects():
    start = World("FloorPlan1").objects
    a, b = World("FloorPlan1", seed=3).objects, World("FloorPlan1", seed=3).objects
    assert a == b
    assert a != start
    others = [World("FloorPlan1", seed=s).objects for s in (4, 5, 6)]
    assert any(o != a for o in others)
    moved = [i for i, (x, y) in enumerate(zip(start, a)) if x.position != y.position]
    assert len(moved) >= 5


@pytest.mark.parametrize(
    "name, seed", [("FloorPlan1", 3), ("FloorPlan1", 11), ("FloorPlan19", 0), ("FloorPlan28", 7)]
)
def test_placements_come_from_real_records(name, seed):
    start = World(name)
    w = World(name, seed=seed)
    placements = w.kitchen.placements

    def matches(record):
        return all(
            w.objects[i].position == (x, y, z) and w.objects[i].yaw == yaw for i, x, y, z, yaw in record
        )

    records = [r for r in placements if matches(r)]
    assert records, "the seeded scene is none of the kitchen's recorded placements"
    placed = {r[0] for r in records[0]}
    for i, (o0, o1) in enumerate(zip(start.objects, w.objects)):
        assert o1.id == o0.id and o1.type == o0.type
        if i not in placed:
            assert (o1.position, o1.footprint, o1.y_range) == (o0.position, o0.footprint, o0.y_range)
            continue
        # a rigid motion: the footprint keeps its area and its distance to the pivot
        assert sum(map(_area, o1.footprint)) == pytest.approx(sum(map(_area, o0.footprint)), abs=1e-6)
        d0 = math.dist(o0.center, (o0.position[0], o0.position[2]))
        d1 = math.dist(o1.center, (o1.position[0], o1.position[2]))
        assert d1 == pytest.approx(d0, abs=1e-6)
        assert o1.y_range[1] - o1.y_range[0] == pytest.approx(o0.y_range[1] - o0.y_range[0])
    # the hidden flags follow the new parents
    for i, o in enumerate(w.objects):
        assert o.hidden == w.is_hidden(i)
        assert o.parent is None or w.object(o.parent).receptacle


def test_seeded_world_behaves_like_any_world():
    w = World("FloorPlan1", seed=3)
    assert w.reachable == World("FloorPlan1").reachable
    w.teleport(Pose(CENTRE, 0, 0))
    assert w.step("MoveAhead").success


# ---------------------------------------------------------------------------------------------------
# bad input


@pytest.mark.parametrize("action", ["Fly", "moveahead", "", "Open", "CloseObject"])
def test_unknown_action_is_named(fp1, action):
    with pytest.raises(WorldError, match=f"unknown action {action!r}"):
        parse_action(action)
    with pytest.raises(WorldError, match=f"unknown action {action!r}"):
        fp1.step(action)
    assert all(parse_action(a) == a for a in ACTIONS)


def test_teleport_rejects_bad_poses(fp1):
    before = fp1.pose
    with pytest.raises(WorldError, match=r"\(25\.00, 25\.00\) is not a reachable cell of FloorPlan1"):
        fp1.teleport(Pose((100, 100), 0, 0))
    with pytest.raises(WorldError, match="not a reachable cell"):
        fp1.teleport(Pose((EDGE[0] - 1, EDGE[1]), 0, 0))
    with pytest.raises(WorldError, match="heading 45"):
        fp1.teleport(Pose(CENTRE, 45, 0))
    with pytest.raises(WorldError, match="heading 360"):
        fp1.teleport(Pose(CENTRE, 360, 0))
    for pitch in (15, 90, -60):
        with pytest.raises(WorldError, match=f"pitch {pitch}"):
            fp1.teleport(Pose(CENTRE, 0, pitch))
    assert fp1.pose == before


def test_parse_pose(fp1):
    k = fp1.kitchen
    assert parse_pose("0.25,-1.5,90,0", k) == Pose((1, -6), 90, 0)
    assert parse_pose("-1.00, 1.00, 270, 30", k) == FACING_FRIDGE
    assert parse_pose("-1,-1.5", k) == Pose((-4, -6), 0, 0)
    assert str(FACING_FRIDGE) == "-1.00,1.00,270,30"
    assert parse_pose(str(FACING_FRIDGE), k) == FACING_FRIDGE


@pytest.mark.parametrize(
    "text", ["", "abc", "1", "1,2,3,4,5", "0.25;0.5", "x,0", "nan,0", "inf,0", "0,0,90.5"]
)
def test_parse_pose_rejects_garbage(fp1, text):
    with pytest.raises(WorldError, match="bad pose"):
        parse_pose(text, fp1.kitchen)


@pytest.mark.parametrize("text", ["0.1,0.25", "0.25,0.3", "0.125,0,0,0"])
def test_parse_pose_rejects_off_grid(fp1, text):
    with pytest.raises(WorldError, match="0.25 m grid"):
        parse_pose(text, fp1.kitchen)


def test_unknown_object_id_is_named(fp1):
    for call in (fp1.index, fp1.object, fp1.open):
        with pytest.raises(WorldError, match=r"FloorPlan1 has no object 'Egg\|\+09\.99'"):
            call("Egg|+09.99")


def test_unknown_kitchen_is_named():
    with pytest.raises(KitchenError, match="FloorPlan31"):
        World("FloorPlan31")
