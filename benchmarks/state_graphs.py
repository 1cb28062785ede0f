"""Seconds to build the state graph (states, transitions, visibility, open twins) and the targets'
BFS distances for every kitchen. Run: .venv/bin/python benchmarks/state_graphs.py [--kitchens A,B]
"""

import argparse
import time

import numpy as np

from kgnavbench.kitchens import KITCHEN_NAMES
from kgnavbench.tasks import bfs_distances, build_state_graph, find_targets
from kgnavbench.world import World


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitchens", default=",".join(KITCHEN_NAMES))
    args = ap.parse_args()
    total_start = time.perf_counter()
    n_states = n_targets = 0
    for name in args.kitchens.split(","):
        start = time.perf_counter()
        graph = build_state_graph(World(name))
        built = time.perf_counter() - start
        targets = find_targets(graph)
        for t in targets:
            bfs_distances(graph.next, np.isin(np.arange(graph.n_states), t.goal_states))
        n_states += graph.n_states
        n_targets += len(targets)
        kinds = sum(t.kind == "actionable" for t in targets)
        print(
            f"{name:12s} {graph.n_states:5d} states {len(targets):3d} targets ({kinds} actionable) "
            f"graph {built:5.2f} s, with BFS {time.perf_counter() - start:5.2f} s"
        )
    total = time.perf_counter() - total_start
    print(
        f"all: {n_states} states, {n_targets} targets in {total:.1f} s "
        f"({n_states / total:.0f} states/s); 84x84 view caching is not part of this yet"
    )


if __name__ == "__main__":
    main()
