"""The state graph, BFS distances and targets (tasks stage)."""

import numpy as np
import pytest

from kgnavbench.tasks import OPEN, STOP, bfs_distances, build_state_graph, find_targets
from kgnavbench.world import ACTIONS, Pose, World

EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"


def test_bfs_on_a_hand_made_graph():
    # a corridor 0-1-2-3 with a one-way shortcut 0 -> 3 and a dead end 4 that only leads to itself
    #   action 0: right, action 1: left, action 2: shortcut (only from 0)
    nxt = np.array([[1, 0, 3], [2, 0, 1], [3, 1, 2], [3, 2, 3], [4, 4, 4]])
    goal = np.array([False, False, False, True, False])
    assert bfs_distances(nxt, goal).tolist() == [1, 2, 1, 0, -1]
    goal = np.array([True, False, False, False, False])
    assert bfs_distances(nxt, goal).tolist() == [0, 1, 2, 3, -1]


@pytest.fixture(scope="module")
def graph():
    return build_state_graph(World("FloorPlan1"))


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
            assert graph.pose(int(graph.next[s, a])) == result.pose
            assert bool(graph.ok[s, a]) == result.success


def test_open_states_close_on_any_action_but_stop(graph):
    opened = np.flatnonzero(graph.opened >= 0)
    assert len(opened) > 0
    for o in opened[:50]:
        assert graph.next[o, STOP] == o
        assert graph.next[o, OPEN] == o
        closed = graph.state_of(graph.pose(int(o)))
        for a in range(len(ACTIONS)):
            if a not in (STOP, OPEN):
                assert graph.next[o, a] == graph.next[closed, a]
                assert graph.opened[graph.next[o, a]] == -1


def test_the_egg_is_an_actionable_target_seen_only_with_the_fridge_open(graph):
    targets = {t.object_id: t for t in find_targets(graph)}
    egg = targets[EGG]
    assert egg.kind == "actionable"
    fridge = graph.world.index(FRIDGE)
    assert all(graph.opened[s] == fridge for s in egg.goal_states)
    assert egg.destination in egg.goal_states
    dist = bfs_distances(graph.next, np.isin(np.arange(graph.n_states), egg.goal_states))
    start = graph.state_of(Pose((-4, 4), 270, 30))
    assert dist[start] == 1  # OpenObject, facing the fridge
    assert dist[graph.next[start, ACTIONS.index("RotateRight")]] == 2
    assert targets[FRIDGE].kind == "static"
    assert all(graph.opened[s] == -1 for s in targets[FRIDGE].goal_states)
