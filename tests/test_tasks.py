"""The state graph, BFS distances and targets (tasks stage)."""

import gzip
import hashlib
import json
import random
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from kgnavbench import graph as graph_stage
from kgnavbench import tasks
from kgnavbench.files import checksum_path
from kgnavbench.graph import (
    OPEN,
    STOP,
    TaskError,
    bfs_distances,
    expert_actions,
    goal_mask,
    load_graph,
    shortest_trajectory,
    walk_back_trajectory,
)
from kgnavbench.kitchens import KITCHEN_NAMES
from kgnavbench.tasks import (
    EPISODES_PER_TARGET,
    MIN_START_DISTANCE,
    SEEN_TARGETS_PER_KITCHEN,
    START_PITCH,
    TASKS_FORMAT,
    Target,
    find_targets,
    kitchen_task_record,
    load_task_file,
    seen_targets,
    split_kitchens,
)
from kgnavbench.world import ACTIONS, Pose, World

EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"
APPLE = "Apple|-00.47|+01.15|+00.48"
MOVE_AHEAD, MOVE_RIGHT, ROTATE_LEFT = (ACTIONS.index(a) for a in ("MoveAhead", "MoveRight", "RotateLeft"))

# a corridor 0-1-2-3 with a one-way shortcut 0 -> 3 and a dead end 4 that only leads to itself
#   action 0: right, action 1: left, action 2: shortcut (only from 0)
CORRIDOR = np.array([[1, 0, 3], [2, 0, 1], [3, 1, 2], [3, 2, 3], [4, 4, 4]])


def test_bfs_on_a_hand_made_graph():
    goal = np.array([False, False, False, True, False])
    assert bfs_distances(CORRIDOR, goal).tolist() == [1, 2, 1, 0, -1]
    goal = np.array([True, False, False, False, False])
    assert bfs_distances(CORRIDOR, goal).tolist() == [0, 1, 2, 3, -1]


def test_expert_actions_on_a_hand_made_graph():
    dist = bfs_distances(CORRIDOR, goal_mask(5, [3]))
    # 0 takes the shortcut, 1 and 2 go right, 3 is the goal (Stop), 4 cannot reach it
    assert expert_actions(CORRIDOR, dist).tolist() == [2, 0, 0, STOP, -1]
    assert shortest_trajectory(CORRIDOR, dist, 0) == [2, STOP]
    assert shortest_trajectory(CORRIDOR, dist, 1) == [0, 0, STOP]
    assert shortest_trajectory(CORRIDOR, dist, 3) == [STOP]
    with pytest.raises(TaskError, match="state 4 cannot reach the goal"):
        shortest_trajectory(CORRIDOR, dist, 4)

    dist = bfs_distances(CORRIDOR, goal_mask(5, [0]))
    assert expert_actions(CORRIDOR, dist).tolist() == [STOP, 1, 1, 1, -1]
    assert shortest_trajectory(CORRIDOR, dist, 3) == [1, 1, 1, STOP]


def test_expert_breaks_ties_by_the_first_action():
    # from 0 both action 0 (to 1) and action 1 (to 2) lead one step nearer to 3; action 2 stays put
    nxt = np.array([[1, 2, 0], [3, 3, 1], [3, 3, 2], [3, 3, 3]])
    dist = bfs_distances(nxt, goal_mask(4, [3]))
    assert dist.tolist() == [2, 1, 1, 0]
    assert expert_actions(nxt, dist).tolist() == [0, 0, 0, STOP]
    assert shortest_trajectory(nxt, dist, 0) == [0, 0, STOP]


@pytest.fixture(scope="module")
def graph(floorplan1_tasks):
    return floorplan1_tasks.graph


def test_transitions_follow_the_world(graph):
    world = World("FloorPlan1")
    rng = np.random.default_rng(0)
    for s in rng.choice(graph.n_states, 60, replace=False):
        s = int(s)
        if graph.opened[s] >= 0:
            continue
        for a, action in enumerate(ACTIONS):
            if a == OPEN:
                continue
            world.teleport(graph.pose(s))
            result = world.step(action)
            assert graph.pose(int(graph.next_state[s, a])) == result.pose
            assert bool(graph.ok[s, a]) == result.success


def test_open_states_close_on_any_action_but_stop(graph):
    opened = np.flatnonzero(graph.opened >= 0)
    assert len(opened) > 0
    for o in opened[:50]:
        assert graph.next_state[o, STOP] == o
        assert graph.next_state[o, OPEN] == o
        closed = graph.state_of(graph.pose(int(o)))
        for a in range(len(ACTIONS)):
            if a not in (STOP, OPEN):
                assert graph.next_state[o, a] == graph.next_state[closed, a]
                assert graph.opened[graph.next_state[o, a]] == -1


def test_the_egg_is_an_actionable_target_seen_only_with_the_fridge_open(graph):
    targets = {t.object_id: t for t in find_targets(graph)}
    egg = targets[EGG]
    assert egg.kind == "actionable"
    fridge = graph.world.index(FRIDGE)
    assert all(graph.opened[s] == fridge for s in egg.goal_states)
    assert egg.destination in egg.goal_states
    dist = bfs_distances(graph.next_state, np.isin(np.arange(graph.n_states), egg.goal_states))
    start = graph.state_of(Pose((-4, 4), 270, 30))
    assert dist[start] == 1  # OpenObject, facing the fridge
    assert dist[graph.next_state[start, ACTIONS.index("RotateRight")]] == 2
    assert targets[FRIDGE].kind == "static"
    assert graph.opened[targets[FRIDGE].destination] == -1  # its image shows it closed


def test_goal_states_are_every_state_showing_the_target_open_or_closed(graph):
    """A static target seen while some receptacle is open (the Fridge itself after OpenObject in
    front of it) is in view there, so that state is a goal state too."""
    targets = find_targets(graph)
    fridge = {t.object_id: t for t in targets}[FRIDGE]
    index = graph.world.index(FRIDGE)
    showing = [s for s in range(graph.n_states) if index in graph.visible[s].visible]
    assert sorted(fridge.goal_states) == showing
    open_goals = [s for s in fridge.goal_states if graph.opened[s] >= 0]
    assert open_goals, "the open Fridge is in view in front of it"
    # every target: goal states are exactly the states where it is visible
    for t in targets:
        assert set(t.goal_states) == set(np.flatnonzero(graph.visible_mask(t.object_index)).tolist())
    static_open = [
        t for t in targets if t.kind == "static" and any(graph.opened[s] >= 0 for s in t.goal_states)
    ]
    assert len(static_open) >= 20


# ------------------------------------------------------------------------------------------------
# Shortest paths and experts on FloorPlan1


@pytest.mark.parametrize("object_id", [EGG, APPLE, FRIDGE])
@pytest.mark.parametrize("rule", ["visible", "destination"])
def test_distances_satisfy_bellman(floorplan1_tasks, object_id, rule):
    graph = floorplan1_tasks.graph
    target = floorplan1_tasks.target(object_id)
    dist = floorplan1_tasks.distances(target, rule)
    goals = target.goal_states if rule == "visible" else (target.destination,)
    assert set(np.flatnonzero(dist == 0).tolist()) == set(goals)
    inf = np.where(dist < 0, np.iinfo(np.int64).max, dist)
    best_next = inf[graph.next_state].min(axis=1)
    far = dist > 0
    # every state one step from the goal is exactly one further than its best successor ...
    assert (best_next[far] == dist[far] - 1).all()
    # ... and a state that cannot reach it only leads to states that cannot either
    assert (dist[graph.next_state[dist < 0]] < 0).all()
    best = expert_actions(graph.next_state, dist)
    assert (best[dist == 0] == STOP).all()
    assert (best[dist < 0] == -1).all()
    assert (dist[graph.next_state[far, best[far]]] == dist[far] - 1).all()


@pytest.mark.parametrize("object_id", [EGG, APPLE, FRIDGE])
def test_shortest_trajectory_reaches_the_goal_in_dist_actions(floorplan1_tasks, object_id):
    graph = floorplan1_tasks.graph
    target = floorplan1_tasks.target(object_id)
    dist = floorplan1_tasks.distances(target)
    for start in target.starts[:10]:
        actions = shortest_trajectory(graph.next_state, dist, start)
        assert len(actions) == dist[start] + 1
        assert actions[-1] == STOP
        assert STOP not in actions[:-1]
        s = start
        for a in actions[:-1]:
            assert graph.ok[s, a]
            s = int(graph.next_state[s, a])
        assert s in target.goal_states
        assert graph.next_state[s, STOP] == s  # the final Stop keeps it there


@pytest.mark.parametrize("object_id", [EGG, APPLE])
@pytest.mark.parametrize("n_steps", [0, 1, 12, 40])
def test_walk_back_trajectory_ends_at_the_destination(floorplan1_tasks, object_id, n_steps):
    graph = floorplan1_tasks.graph
    target = floorplan1_tasks.target(object_id)
    actionable = target.kind == "actionable"
    assert actionable == (object_id == EGG)
    start, actions = walk_back_trajectory(graph, target.destination, n_steps)
    assert graph.opened[start] == -1  # the walk starts with every receptacle closed
    assert actions[-1] == STOP
    walk = actions[:-1]
    if actionable:
        assert walk[-1] == OPEN
        walk = walk[:-1]
    assert len(walk) == n_steps
    assert set(walk) <= {MOVE_AHEAD, MOVE_RIGHT, ROTATE_LEFT}
    s = start
    for a in actions:
        assert graph.ok[s, a], f"{ACTIONS[a]} fails in {graph.pose(s)}"
        s = int(graph.next_state[s, a])
    assert s == target.destination


def test_walk_back_trajectory_hand_checked(floorplan1_tasks):
    """The paper's expert for FloorPlan1's StoveBurner (destination x 0.00, z -1.75, facing 180 = -z,
    looking 30 down), 12 steps, checked by hand on the reachable grid: MoveBack (+z) twice to z -1.25,
    where the next cell behind is blocked; MoveLeft (facing -z, left is +x) four times to x 1.00;
    MoveBack once to z -1.00, blocked again; MoveLeft once to x 1.25; MoveBack four times to z 0.00.
    Reversed: MoveAhead x4, MoveRight, MoveAhead, MoveRight x4, MoveAhead x2, then Stop."""
    graph = floorplan1_tasks.graph
    target = next(t for t in floorplan1_tasks.targets if t.object_id.startswith("StoveBurner|-00.04"))
    assert graph.pose(target.destination) == Pose((0, -7), 180, 30)  # cells of 0.25 m
    start, actions = walk_back_trajectory(graph, target.destination, 12)
    assert graph.pose(start) == Pose((5, 0), 180, 30)
    names = [ACTIONS[a] for a in actions]
    assert names == ["MoveAhead"] * 4 + ["MoveRight", "MoveAhead"] + ["MoveRight"] * 4 + ["MoveAhead"] * 2 + [
        "Stop"
    ]
    poses, s = [], start
    for a in actions:
        poses.append(graph.pose(s))
        s = int(graph.next_state[s, a])
    assert poses[4:7] == [Pose((5, -4), 180, 30), Pose((4, -4), 180, 30), Pose((4, -5), 180, 30)]
    assert s == target.destination


def test_walk_back_prefers_move_back(floorplan1_tasks):
    # one step back from the destination: MoveBack if it can, so the expert's only move is MoveAhead
    graph = floorplan1_tasks.graph
    destination = floorplan1_tasks.target(APPLE).destination
    back, left = ACTIONS.index("MoveBack"), ACTIONS.index("MoveLeft")
    start, actions = walk_back_trajectory(graph, destination, 1)
    if graph.ok[destination, back]:
        expected = MOVE_AHEAD, graph.next_state[destination, back]
    elif graph.ok[destination, left]:
        expected = MOVE_RIGHT, graph.next_state[destination, left]
    else:
        expected = ROTATE_LEFT, graph.next_state[destination, ACTIONS.index("RotateRight")]
    assert (actions, start) == ([expected[0], STOP], expected[1])


# ------------------------------------------------------------------------------------------------
# The task file: splits, targets, fixed episodes


@pytest.fixture(scope="module")
def task_file():
    return load_task_file()


def _actionable_counts(record):
    return {k: sum(t["kind"] == "actionable" for t in r["targets"]) for k, r in record["kitchens"].items()}


def test_task_file_splits_the_30_kitchens(task_file):
    assert task_file["format"] == TASKS_FORMAT
    assert task_file["episodes_per_target"] == EPISODES_PER_TARGET == 100
    assert task_file["min_start_distance"] == MIN_START_DISTANCE
    assert sorted(task_file["kitchens"], key=KITCHEN_NAMES.index) == list(KITCHEN_NAMES)
    assert len(KITCHEN_NAMES) == 30
    splits = task_file["splits"]
    assert {k: len(v) for k, v in splits.items()} == {"train": 20, "val": 5, "test": 5}
    everything = splits["train"] + splits["val"] + splits["test"]
    assert len(set(everything)) == 30
    assert set(everything) == set(KITCHEN_NAMES)


def test_train_kitchens_have_the_most_actionable_targets(task_file):
    counts = _actionable_counts(task_file)
    assert task_file["splits"] == split_kitchens(counts)
    train = task_file["splits"]["train"]
    rest = [k for k in KITCHEN_NAMES if k not in train]
    assert min(counts[k] for k in train) >= max(counts[k] for k in rest)
    # a tie at the boundary goes to the lower FloorPlan number
    boundary = min(counts[k] for k in train)
    tied_train = [KITCHEN_NAMES.index(k) for k in train if counts[k] == boundary]
    tied_rest = [KITCHEN_NAMES.index(k) for k in rest if counts[k] == boundary]
    if tied_rest:
        assert max(tied_train) < min(tied_rest)


def test_split_kitchens_rules():
    counts = {k: 0 for k in KITCHEN_NAMES}
    counts.update({"FloorPlan30": 9, "FloorPlan29": 8})
    splits = split_kitchens(counts)
    assert splits["train"][-2:] == ["FloorPlan29", "FloorPlan30"]  # sorted by FloorPlan number
    assert splits["train"][:18] == list(KITCHEN_NAMES[:18])  # ties: the lower numbers
    rest = list(KITCHEN_NAMES[18:28])
    assert splits["val"] == rest[0::2] and splits["test"] == rest[1::2]


def test_every_target_has_100_fixed_episodes(task_file):
    for kitchen, record in task_file["kitchens"].items():
        assert record["targets"], kitchen
        ids = [t["object"] for t in record["targets"]]
        assert len(ids) == len(set(ids)), kitchen
        for t in record["targets"]:
            assert len(t["starts"]) == EPISODES_PER_TARGET, (kitchen, t["object"])
            assert t["kind"] in ("static", "actionable")
            assert isinstance(t["seen"], bool)
            assert all(0 <= s < record["n_states"] for s in t["starts"])
            assert 0 <= t["destination"] < record["n_states"]


def test_floorplan1_starts_are_closed_level_and_far(floorplan1_tasks):
    graph = floorplan1_tasks.graph
    assert floorplan1_tasks.split == "train"
    assert len(floorplan1_tasks.targets) > 0
    for t in floorplan1_tasks.targets:
        starts = np.array(t.starts)
        assert len(starts) == EPISODES_PER_TARGET
        assert (starts < graph.n_closed).all()
        assert (graph.opened[starts] == -1).all()
        assert (graph.pitch[starts] == START_PITCH).all()
        assert (floorplan1_tasks.distances(t, "destination")[starts] >= MIN_START_DISTANCE).all()


def test_floorplan1_record_regenerates_identically(graph, task_file):
    record = kitchen_task_record(graph, training=True)
    committed = task_file["kitchens"]["FloorPlan1"]
    assert record["n_states"] == committed["n_states"] == graph.n_states
    assert record["fingerprint"] == committed["fingerprint"]
    assert record["targets"] == committed["targets"]
    assert record["dropped"] == committed["dropped"]
    assert record == committed


# What FloorPlan1's state graph holds at GRAPH_VERSION, hashed (states, transitions, visibility, every
# 50th view). The graph's fingerprint, which names the cached graphs and stands in the task file, comes
# from GRAPH_VERSION, the kitchen file and graph.graph_parameters, no longer from the code's bytes: so
# a change of the code that changes what a graph holds must bump GRAPH_VERSION, and this test says when.
GOLDEN_GRAPH = (2, "eb89153cd3118584c5ba4c99537c331c1e2fbddfd4e59979aea8ec6498a8b878")


def graph_content_sha256(g) -> str:
    h = hashlib.sha256()
    for array in (np.array(g.cells, np.int64), g.cell, g.heading, g.pitch, g.opened, g.next_state, g.ok):
        h.update(np.ascontiguousarray(array).astype(np.int64).tobytes())
    for v in g.visible:
        h.update(repr((v.visible, v.pixels, v.open_target)).encode())
    h.update(np.ascontiguousarray(g.views[::50]).tobytes())
    return h.hexdigest()


def test_a_change_of_what_a_graph_holds_bumps_graph_version(graph):
    """FloorPlan1's graph, built by this code in the test's fresh cache, is the one recorded for this
    GRAPH_VERSION; the fingerprint keeps today's value for today's graphs (no saved evaluation lost)."""
    got = (graph_stage.GRAPH_VERSION, graph_content_sha256(graph))
    assert got == GOLDEN_GRAPH, (
        "what FloorPlan1's state graph holds has changed: bump graph.GRAPH_VERSION and record "
        f"GOLDEN_GRAPH = {(graph_stage.GRAPH_VERSION + 1, got[1])}"
        if got[0] == GOLDEN_GRAPH[0]
        else f"GRAPH_VERSION was bumped: record GOLDEN_GRAPH = {got}"
    )
    assert graph_stage.graph_fingerprint("FloorPlan1") == "532a5d1efb367775"  # the recorded one
    # an input that decides the graph gives another fingerprint
    graph_stage.graph_fingerprint.cache_clear()
    try:
        with pytest.MonkeyPatch.context() as m:
            m.setattr(graph_stage, "GRAPH_VERSION", graph_stage.GRAPH_VERSION + 1)
            assert graph_stage.graph_fingerprint("FloorPlan1") != "532a5d1efb367775"
        graph_stage.graph_fingerprint.cache_clear()
        with pytest.MonkeyPatch.context() as m:
            m.setattr(graph_stage.render_module, "MIN_VISIBLE_PIXELS", 7)
            assert graph_stage.graph_fingerprint("FloorPlan1") != "532a5d1efb367775"
    finally:
        graph_stage.graph_fingerprint.cache_clear()
    assert graph_stage.graph_fingerprint("FloorPlan1") == "532a5d1efb367775"


def test_the_papers_split_140_seen_targets_all_actionable_first(task_file):
    """20 training kitchens x 7 seen targets; every actionable target of a training kitchen is seen;
    validation and test kitchens have no seen targets (the "unseen kitchens" column)."""
    splits = task_file["splits"]
    total = 0
    for kitchen in splits["train"]:
        targets = task_file["kitchens"][kitchen]["targets"]
        seen = [t for t in targets if t["seen"]]
        assert len(seen) == SEEN_TARGETS_PER_KITCHEN, kitchen
        assert all(t["seen"] for t in targets if t["kind"] == "actionable"), kitchen
        total += len(seen)
    assert total == 140
    for kitchen in splits["val"] + splits["test"]:
        assert not any(t["seen"] for t in task_file["kitchens"][kitchen]["targets"]), kitchen


def _fake_targets(n_static, n_actionable):
    kinds = ["static"] * n_static + ["actionable"] * n_actionable
    return [Target(i, f"Thing|{i:03d}", "Thing", kind, i, (i,)) for i, kind in enumerate(kinds)]


@pytest.mark.parametrize(("n_static", "n_actionable"), [(9, 5), (4, 1), (1, 0), (0, 0), (30, 3), (2, 9)])
def test_seen_targets_are_the_actionable_ones_then_seeded_static_ones(n_static, n_actionable):
    targets = _fake_targets(n_static, n_actionable)
    seen = seen_targets("FloorPlan7", targets)
    kind = {t.object_id: t.kind for t in targets}
    per_kind = Counter(kind[o] for o in seen)
    assert per_kind["actionable"] == n_actionable
    assert per_kind["static"] == min(n_static, max(0, SEEN_TARGETS_PER_KITCHEN - n_actionable))
    # deterministic, and independent of the order the targets come in
    shuffled = targets[:]
    random.Random(1).shuffle(shuffled)
    assert seen_targets("FloorPlan7", shuffled) == seen
    assert seen_targets("FloorPlan7", list(reversed(targets))) == seen


def test_seen_targets_depend_on_the_kitchen():
    targets = _fake_targets(40, 0)
    picks = {frozenset(seen_targets(k, targets)) for k in KITCHEN_NAMES[:5]}
    assert len(picks) > 1


def test_seen_targets_of_floorplan1_match_the_task_file(graph, task_file):
    seen = seen_targets("FloorPlan1", find_targets(graph))
    committed = {t["object"] for t in task_file["kitchens"]["FloorPlan1"]["targets"] if t["seen"]}
    assert seen == committed


# ------------------------------------------------------------------------------------------------
# The on-disk cache of state graphs


def _assert_same_graph(a, b):
    assert a.kitchen == b.kitchen
    assert a.cells == b.cells
    for name in ("cell", "heading", "pitch", "opened", "next_state", "ok", "views", "object_vectors"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.visible == b.visible


def test_second_call_loads_the_graph_from_disk(graph, monkeypatch):
    def no_build(*args, **kwargs):
        raise AssertionError("the cached graph should have been loaded, not rebuilt")

    monkeypatch.setattr(graph_stage, "build_state_graph", no_build)
    loaded = graph_stage.state_graph("FloorPlan1")
    assert loaded is not graph
    assert isinstance(loaded.views, np.memmap)  # memory-mapped from the cache file
    _assert_same_graph(loaded, graph)


@pytest.fixture
def cache_copy(graph, tmp_path):
    """A private copy of FloorPlan1's cache files, safe to corrupt."""
    sources = graph_stage._cache_paths("FloorPlan1", graph.views.shape[1], graph_stage.cache_dir())
    copies = graph_stage._cache_paths("FloorPlan1", graph.views.shape[1], tmp_path)
    for source, copy in zip(sources, copies):
        assert source.exists()
        shutil.copyfile(source, copy)
        shutil.copyfile(checksum_path(source), checksum_path(copy))  # a copy with its checksum is trusted
    return tmp_path, copies


def test_cache_copy_is_readable(graph, cache_copy):
    root, _ = cache_copy
    _assert_same_graph(load_graph("FloorPlan1", root=root), graph)


@pytest.mark.parametrize(
    "damage",
    [
        "garbage graph",
        "truncated graph",
        "garbage views",
        "truncated views",
        "views of too few states",
        "missing views",
        "missing graph",
    ],
)
def test_damaged_cache_files_are_not_trusted(graph, cache_copy, damage):
    root, (graph_path, views_path) = cache_copy
    path = graph_path if "graph" in damage else views_path
    if damage.startswith("garbage"):
        path.write_bytes(b"this is not a numpy file" * 100)
    elif damage.startswith("truncated"):
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage.startswith("missing"):
        path.unlink()
    else:
        np.save(views_path, np.zeros((10, *graph.views.shape[1:]), np.uint8))
    assert load_graph("FloorPlan1", root=root) is None


def test_corrupt_cache_is_rebuilt_with_the_same_result(graph, cache_copy, monkeypatch, capsys):
    root, (graph_path, _) = cache_copy
    graph_path.write_bytes(b"\x00garbage\xff" * 1000)
    builds = []
    real_build = graph_stage.build_state_graph

    def counting_build(*args, **kwargs):
        builds.append(args)
        return real_build(*args, **kwargs)

    monkeypatch.setattr(graph_stage, "build_state_graph", counting_build)
    rebuilt = graph_stage.state_graph("FloorPlan1", root=root)
    assert len(builds) == 1
    out, err = capsys.readouterr()
    assert "cannot be trusted" in err and not out  # stdout stays clean for --json
    _assert_same_graph(rebuilt, graph)
    # the rebuilt graph replaced the corrupt file, and the session cache was never touched
    _assert_same_graph(load_graph("FloorPlan1", root=root), graph)
    _assert_same_graph(load_graph("FloorPlan1"), graph)


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("KGNAVBENCH_CACHE", str(tmp_path / "k"))
    assert graph_stage.cache_dir() == tmp_path / "k"
    monkeypatch.delenv("KGNAVBENCH_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert graph_stage.cache_dir() == tmp_path / "xdg" / "kgnavbench"


# ------------------------------------------------------------------------------------------------
# Bad task files


def _write_gz(path, payload: bytes):
    path.write_bytes(gzip.compress(payload))
    return path


def _good_record(**changes):
    record = {"format": TASKS_FORMAT, "splits": {}, "kitchens": {}}
    record.update(changes)
    return json.dumps(record).encode()


@pytest.mark.parametrize(
    ("make", "why"),
    [
        (lambda p: p.write_bytes(b"\x00\x01 garbage bytes \xff" * 50), "BadGzipFile"),
        (lambda p: p.write_bytes(tasks.TASKS_FILE.read_bytes()[:5000]), "EOFError"),
        (lambda p: _write_gz(p, b"{not json"), "JSONDecodeError"),
        (lambda p: _write_gz(p, b"\xff\xfe\xfa"), "UnicodeDecodeError"),
        (lambda p: _write_gz(p, b"[1, 2]"), "AttributeError"),
        (lambda p: _write_gz(p, _good_record(format=TASKS_FORMAT + 1)), f"format {TASKS_FORMAT + 1}"),
        (lambda p: _write_gz(p, _good_record(format=None)), "format None"),
        (lambda p: _write_gz(p, _good_record(splits=[])), "no 'splits' table"),
        (lambda p: _write_gz(p, _good_record(kitchens=None)), "no 'kitchens' table"),
    ],
)
def test_corrupt_task_file_is_reported(tmp_path, make, why):
    path = tmp_path / "tasks.json.gz"
    make(path)
    with pytest.raises(TaskError) as info:
        load_task_file(path)
    message = str(info.value)
    assert str(path) in message
    assert "corrupt" in message and why in message
    assert "make tasks" in message


def test_missing_task_file_is_reported(tmp_path):
    path = tmp_path / "nowhere" / "tasks.json.gz"
    with pytest.raises(TaskError, match="make tasks") as info:
        load_task_file(path)
    assert str(path) in str(info.value)
    assert "missing" in str(info.value)


def test_a_good_task_file_elsewhere_loads(tmp_path):
    path = _write_gz(tmp_path / "tasks.json.gz", _good_record())
    assert load_task_file(path) == {"format": TASKS_FORMAT, "splits": {}, "kitchens": {}}


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc (Linux)")
def test_killing_prepare_leaves_no_worker_processes(tmp_path):
    """kill -9 of `kgnavbench prepare` ends its pool's workers too (each watches its parent), rather than
    leaving them to build state graphs for nobody."""
    import os
    import signal
    import subprocess
    import sys
    import time

    env = {**os.environ, "KGNAVBENCH_CACHE": str(tmp_path / "cache")}
    argv = [
        sys.executable,
        "-m",
        "kgnavbench",
        "prepare",
        "--kitchens",
        "FloorPlan2,FloorPlan3",
        "--workers",
        "2",
    ]
    parent = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def children() -> list[int]:
        out = subprocess.run(["pgrep", "-P", str(parent.pid)], capture_output=True, text=True).stdout
        return [int(pid) for pid in out.split()]

    deadline = time.time() + 60
    while len(children()) < 2 and time.time() < deadline:
        time.sleep(0.2)
    workers = children()
    assert len(workers) >= 2, "the pool did not start"
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.time() + 10
    alive = workers
    while alive and time.time() < deadline:
        time.sleep(0.2)
        alive = [w for w in workers if os.path.exists(f"/proc/{w}") and "Z" not in _proc_state(w)]
    assert not alive, f"workers {alive} outlived their parent"


def _proc_state(pid: int) -> str:
    try:
        return open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "Z"
