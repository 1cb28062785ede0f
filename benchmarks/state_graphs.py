"""Seconds to build, from nothing, what every step and evaluation looks up: each kitchen's state graph
(transitions, visibility, open twins), its cached 84x84 views, its targets and their BFS distances.

It builds into a fresh temporary cache (the real one is untouched), one process per core, as
`kgnavbench prepare` does. Run: .venv/bin/python benchmarks/state_graphs.py [--kitchens A,B]
"""

import argparse
import tempfile
import time
from pathlib import Path

from kgnavbench.graph import bfs_distances, build_all, goal_mask, state_graph
from kgnavbench.kitchens import KITCHEN_NAMES
from kgnavbench.tasks import find_targets


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitchens", default=",".join(KITCHEN_NAMES))
    ap.add_argument("--workers", type=int, default=None, help="processes (default: one per core)")
    args = ap.parse_args()
    kitchens = args.kitchens.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        start = time.perf_counter()
        n_states = 0
        for name, seconds, n in build_all(kitchens, root=root, workers=args.workers):
            n_states += n
            print(f"{name:12s} {n:5d} states, graph + views {seconds:5.1f} s", flush=True)
        built = time.perf_counter() - start
        n_targets = 0
        for name in kitchens:
            graph = state_graph(name, root=root)
            targets = find_targets(graph)
            for t in targets:
                bfs_distances(graph.next_state, goal_mask(graph.n_states, t.goal_states))
                bfs_distances(graph.next_state, goal_mask(graph.n_states, [t.destination]))
            n_targets += len(targets)
        total = time.perf_counter() - start
        size = sum(p.stat().st_size for p in root.iterdir()) / 1e9
    print(
        f"all: {len(kitchens)} kitchens, {n_states} states, {n_targets} targets: graphs + 84x84 views "
        f"{built:.1f} s, with targets and BFS (both rules) {total:.1f} s; cache {size:.2f} GB"
    )


if __name__ == "__main__":
    main()
