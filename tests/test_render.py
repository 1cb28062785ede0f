"""Stage 3 — render: 2.5D views, the instance buffer, visibility (pixels, distance, occlusion, closed
receptacles), pitch and heading, the top-down map."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kgnavbench import render
from kgnavbench.kitchens import KITCHEN_NAMES
from kgnavbench.render import MIN_VISIBLE_PIXELS, VISIBILITY_SIZE, render_views, visible_objects
from kgnavbench.world import EYE_HEIGHT, HEADINGS, Pose, World

EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"
TOASTER = "Toaster|-01.84|+00.90|+00.13"
COFFEE_MACHINE = "CoffeeMachine|-01.98|+00.90|-00.19"
FACING_FRIDGE = Pose((-4, 4), 270, 30)  # (-1.00, 1.00) facing -x, looking down 30 degrees
CENTRE = (-4, -6)


@pytest.fixture
def fp1() -> World:
    return World("FloorPlan1")


def pixels(world: World, pose: Pose, index: int) -> int:
    _, inst = render_views(world, [pose], VISIBILITY_SIZE)
    return int((inst[0] == index).sum())


def footprint_distance(world: World, pose: Pose, index: int) -> float:
    """Plain-geometry distance from the agent's axis to the nearest footprint vertex or edge."""
    px, pz = pose.x, pose.z
    best = math.inf
    for poly in world.objects[index].footprint:
        for a, b in zip(poly, poly[1:] + poly[:1]):
            L = (b[0] - a[0]) ** 2 + (b[1] - a[1]) ** 2
            t = (
                0.0
                if L == 0
                else max(0.0, min(1.0, ((px - a[0]) * (b[0] - a[0]) + (pz - a[1]) * (b[1] - a[1])) / L))
            )
            best = min(best, math.hypot(px - a[0] - t * (b[0] - a[0]), pz - a[1] - t * (b[1] - a[1])))
    return best


# ---------------------------------------------------------------------------------------------------
# shapes, types, determinism


@pytest.mark.parametrize("width, height", [(84, 84), (300, 300), (120, 90), (64, 100)])
def test_view_and_instance_buffer_shapes(fp1, width, height):
    poses = [Pose(CENTRE, 0, 0), FACING_FRIDGE]
    views, inst = render_views(fp1, poses, width, height)
    assert views.shape == (2, height, width, 3) and views.dtype == np.uint8
    assert inst.shape == (2, height, width) and np.issubdtype(inst.dtype, np.integer)
    assert views.flags["C_CONTIGUOUS"] and inst.flags["C_CONTIGUOUS"]
    # a real picture: many colours, and several objects in the instance buffer
    assert len(np.unique(views[1].reshape(-1, 3), axis=0)) > 20
    assert len(set(np.unique(inst[1]).tolist()) - {-1}) >= 2


def test_render_view_is_the_square_single_pose_view(fp1):
    fp1.teleport(FACING_FRIDGE)
    image = render.render_view(fp1)
    assert image.shape == (84, 84, 3) and image.dtype == np.uint8
    assert np.array_equal(image, render_views(fp1, [FACING_FRIDGE], 84)[0][0])
    assert render.render_view(fp1, Pose(CENTRE, 90, 0), size=300).shape == (300, 300, 3)


def test_batched_views_equal_single_views(fp1):
    poses = [
        Pose(c, h, p)
        for c, h, p in [(CENTRE, 0, 0), ((-4, 4), 270, 30), ((0, -6), 90, 60), ((-5, 2), 180, -30)]
    ]
    views, inst = render_views(fp1, poses, 84)
    for k, pose in enumerate(poses):
        v1, i1 = render_views(fp1, [pose], 84)
        assert np.array_equal(views[k], v1[0]) and np.array_equal(inst[k], i1[0])


def _episode(seed: int | None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    w = World("FloorPlan1", seed=seed)
    w.teleport(Pose((-4, 2), 0, 0))
    actions = ["MoveAhead", "MoveAhead", "RotateLeft", "LookDown", "OpenObject", "Stop", "RotateRight",
               "LookUp", "LookUp", "MoveBack", "OpenObject"]  # fmt: skip
    views, insts, opened = [], [], []
    for action in actions:
        r = render.act(w, action)
        opened.append(r.open_receptacle)
        v, i = render_views(w, [w.pose, Pose(CENTRE, 90, 30)], 84)
        views.append(v)
        insts.append(i)
    assert opened[4] == opened[5] == FRIDGE and opened[6] is None  # the walk opens the fridge, then closes it
    return views, insts


@pytest.mark.parametrize("seed", [None, 5])
def test_same_world_poses_and_actions_give_identical_views(seed):
    v1, i1 = _episode(seed)
    v2, i2 = _episode(seed)
    assert all(a.tobytes() == b.tobytes() for a, b in zip(v1, v2))
    assert all(a.tobytes() == b.tobytes() for a, b in zip(i1, i2))


def test_a_seeded_placement_changes_some_views():
    poses = [Pose(c, h, 30) for c in World("FloorPlan1").kitchen.reachable[::4] for h in HEADINGS]
    _, start = render_views(World("FloorPlan1"), poses, 64)
    _, seeded = render_views(World("FloorPlan1", seed=5), poses, 64)
    assert not np.array_equal(start, seeded)


def test_opening_and_closing_restores_the_view(fp1):
    fp1.teleport(FACING_FRIDGE)
    before = render_views(fp1, [FACING_FRIDGE], 84)
    fp1.open(FRIDGE)
    opened = render_views(fp1, [FACING_FRIDGE], 84)
    fp1.close()
    after = render_views(fp1, [FACING_FRIDGE], 84)
    assert not np.array_equal(before[0], opened[0])
    assert np.array_equal(before[0], after[0]) and np.array_equal(before[1], after[1])


# ---------------------------------------------------------------------------------------------------
# the instance buffer


@pytest.mark.parametrize("name", KITCHEN_NAMES)
def test_instance_ids_are_valid_and_hidden_objects_never_appear(name):
    w = World(name)
    poses = [Pose(c, h, 30) for c in w.kitchen.reachable[::2] for h in HEADINGS]
    _, inst = render_views(w, poses, 48)
    ids = set(np.unique(inst).tolist())
    assert min(ids) >= -1 and max(ids) < len(w.objects)
    hidden = {i for i in range(len(w.objects)) if w.is_hidden(i)}
    assert not ids & hidden, [w.objects[i].id for i in ids & hidden]
    assert len(ids - {-1}) >= 10  # a walk around the kitchen sees plenty of objects


def test_open_fridge_shows_the_egg_but_no_other_hidden_object(fp1):
    egg = fp1.index(EGG)
    fp1.teleport(FACING_FRIDGE)
    assert pixels(fp1, FACING_FRIDGE, egg) == 0
    fp1.open(FRIDGE)
    assert pixels(fp1, FACING_FRIDGE, egg) >= MIN_VISIBLE_PIXELS
    still_hidden = {i for i in range(len(fp1.objects)) if fp1.is_hidden(i)}
    assert still_hidden and egg not in still_hidden
    poses = [Pose(c, h, p) for c in fp1.kitchen.reachable[::3] for h in HEADINGS for p in (0, 60)]
    _, inst = render_views(fp1, poses, 48)
    assert not set(np.unique(inst).tolist()) & still_hidden


# ---------------------------------------------------------------------------------------------------
# visibility: pixels, 1.5 m, occlusion, closed receptacles


def test_a_large_object_beyond_1_5_m_is_not_visible(fp1):
    fridge = fp1.index(FRIDGE)
    far = Pose((-5, -4), 0, 0)  # (-1.25, -1.00) looking along +z at the fridge
    assert pixels(fp1, far, fridge) >= 20 * MIN_VISIBLE_PIXELS
    assert footprint_distance(fp1, far, fridge) > 1.5
    assert fridge not in fp1.objects_within(far)
    assert fridge not in visible_objects(fp1, far)

    near = Pose((-5, -3), 0, 0)  # one step closer
    assert pixels(fp1, near, fridge) >= MIN_VISIBLE_PIXELS
    assert footprint_distance(fp1, near, fridge) < 1.5
    assert fridge in visible_objects(fp1, near)


def test_visible_objects_are_exactly_the_near_objects_with_enough_pixels(fp1):
    for pose in [Pose(CENTRE, h, p) for h in HEADINGS for p in (-30, 30)] + [FACING_FRIDGE]:
        _, inst = render_views(fp1, [pose], VISIBILITY_SIZE)
        counts = np.bincount(inst[0].ravel().astype(np.int64) + 1, minlength=len(fp1.objects) + 1)[1:]
        expected = sorted(
            i
            for i in range(len(fp1.objects))
            if counts[i] >= MIN_VISIBLE_PIXELS
            and footprint_distance(fp1, pose, i) < 1.5
            and not fp1.is_hidden(i)
        )
        assert visible_objects(fp1, pose) == expected, pose


def test_an_object_behind_another_is_not_visible(fp1):
    toaster, machine = fp1.index(TOASTER), fp1.index(COFFEE_MACHINE)
    pose = Pose((-5, -2), 270, 30)  # (-1.25, -0.50) facing -x: the coffee machine stands before the toaster
    assert footprint_distance(fp1, pose, toaster) < 1.5 and not fp1.is_hidden(toaster)
    _, inst = render_views(fp1, [pose], VISIBILITY_SIZE)
    assert (inst[0] == toaster).sum() == 0
    assert machine in visible_objects(fp1, pose) and toaster not in visible_objects(fp1, pose)

    # take the coffee machine away: the toaster shows, on pixels the machine covered
    fp1.space.remove(*fp1.object_shapes[machine])
    fp1.geometry_version += 1
    _, inst2 = render_views(fp1, [pose], VISIBILITY_SIZE)
    revealed = inst2[0] == toaster
    assert revealed.sum() >= 10 * MIN_VISIBLE_PIXELS
    assert (inst[0][revealed] == machine).mean() > 0.9
    assert toaster in visible_objects(fp1, pose)


def test_the_egg_behind_the_closed_fridge_door_is_not_visible(fp1):
    egg, fridge = fp1.index(EGG), fp1.index(FRIDGE)
    # the Egg is near and in front of the camera, but the fridge door is shut
    assert footprint_distance(fp1, FACING_FRIDGE, egg) < 1.5
    _, inst = render_views(fp1, [FACING_FRIDGE], VISIBILITY_SIZE)
    assert (inst[0] == egg).sum() == 0 and (inst[0] == fridge).sum() > 1000
    assert egg not in visible_objects(fp1, FACING_FRIDGE)
    fp1.open(FRIDGE)
    assert egg in visible_objects(fp1, FACING_FRIDGE)


def test_open_target_is_the_visible_openable_nearest_the_centre(fp1):
    fridge = fp1.index(FRIDGE)
    assert render.open_target(fp1, FACING_FRIDGE) == FRIDGE
    _, inst = render_views(fp1, [FACING_FRIDGE], VISIBILITY_SIZE)
    c = VISIBILITY_SIZE // 2
    assert inst[0][c, c] == fridge
    assert render.open_target(fp1, Pose(CENTRE, 0, -30)) is None


# ---------------------------------------------------------------------------------------------------
# headings and pitch


def test_the_four_headings_give_four_different_views(fp1):
    views, _ = render_views(fp1, [Pose(CENTRE, h, 0) for h in HEADINGS], 84)
    for a in range(4):
        for b in range(a + 1, 4):
            assert (views[a] != views[b]).any(axis=-1).mean() > 0.3, (HEADINGS[a], HEADINGS[b])


def test_look_up_and_look_down_differ(fp1):
    views, _ = render_views(fp1, [Pose(CENTRE, 0, -30), Pose(CENTRE, 0, 60)], 84)
    assert (views[0] != views[1]).any(axis=-1).mean() > 0.5


def test_pitch_60_never_sees_above_the_eye_and_pitch_minus_30_does(fp1):
    """At pitch 60 even the top row looks below the horizon: nothing wholly above the eye shows."""
    high = np.array([o.y_range[0] > EYE_HEIGHT for o in fp1.objects] + [False])  # index -1: background
    assert high.any()
    poses = [Pose(c, h, p) for c in fp1.kitchen.reachable[::2] for h in HEADINGS for p in (-30, 60)]
    _, inst = render_views(fp1, poses, 64)
    high_px = high[inst].sum(axis=(1, 2))
    up, down = high_px[0::2], high_px[1::2]
    assert (down == 0).all()
    assert (up > 0).mean() > 0.3


def test_looking_down_shows_more_floor(fp1):
    poses = [Pose(c, h, p) for c in fp1.kitchen.reachable[::2] for h in HEADINGS for p in (-30, 60)]
    _, inst = render_views(fp1, poses, 64)
    lower = (inst[:, 32:, :] == -1).mean(axis=(1, 2))  # background (floor/walls) in the lower half
    up, down = lower[0::2], lower[1::2]
    assert down.mean() > up.mean() + 0.05


# ---------------------------------------------------------------------------------------------------
# top-down map


@pytest.mark.parametrize("size", [128, 300])
def test_top_down_map_has_the_requested_size_and_shows_the_agent(fp1, size):
    a = render.top_down_map(fp1, size, poses=[Pose(CENTRE, 0, 0)])
    b = render.top_down_map(fp1, size, poses=[Pose((-4, 4), 270, 0)])
    assert a.shape == (size, size, 3) and a.dtype == np.uint8
    assert not np.array_equal(a, b)
    path = [Pose(CENTRE, 0, 0), Pose((-4, -5), 0, 0), Pose((-4, -4), 0, 0)]
    assert not np.array_equal(render.top_down_map(fp1, size, poses=[Pose(CENTRE, 0, 0)], path=path), a)


def test_top_down_map_shows_the_egg_only_when_the_fridge_is_open(fp1):
    """The open Fridge's closed box must not be drawn over its contents: the Egg's colour shows."""
    egg = np.array(render.type_colour("Egg"), np.uint8)
    closed = render.top_down_map(fp1, 600, poses=[])
    fp1.open(FRIDGE)
    opened = render.top_down_map(fp1, 600, poses=[])
    fp1.close()
    assert (closed == egg).all(-1).sum() == 0
    assert (opened == egg).all(-1).sum() >= 10


def test_save_rgb_round_trips(tmp_path, fp1):
    cv2 = pytest.importorskip("cv2")
    image = render.render_view(fp1, FACING_FRIDGE)
    path = tmp_path / "view.png"
    render.save_rgb(path, image)
    assert np.array_equal(cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB), image)
    with pytest.raises(OSError):
        render.save_rgb(tmp_path / "missing-dir" / "view.png", image)
