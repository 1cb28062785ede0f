"""Views per second of the pseudo-egocentric renderer, at 84x84 (learning) and 300x300 (people).

Renders every (cell, heading, pitch) state of a few kitchens in batches, as the view cache does, and
prints views/s with the batch size; the figure is for one process (numpy may use its own threads).
Run: make bench   (or .venv/bin/python benchmarks/render_speed.py [--kitchens FloorPlan1,...])
"""

import argparse
import time

from kgnavbench.render import render_views
from kgnavbench.world import HEADINGS, PITCHES, Pose, World


def views_per_second(world: World, poses: list[Pose], size: int, batch: int, seconds: float) -> float:
    done, start = 0, time.perf_counter()
    while True:
        for i in range(0, len(poses), batch):
            render_views(world, poses[i : i + batch], size)
            done += len(poses[i : i + batch])
            if time.perf_counter() - start > seconds:
                return done / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitchens", default="FloorPlan1,FloorPlan7,FloorPlan16,FloorPlan28")
    ap.add_argument("--seconds", type=float, default=3.0, help="per kitchen and size")
    args = ap.parse_args()
    for size, batches in ((84, (1, 32)), (300, (1, 8))):
        for batch in batches:
            rates = []
            for name in args.kitchens.split(","):
                world = World(name)
                poses = [Pose(c, h, p) for c in world.kitchen.reachable for h in HEADINGS for p in PITCHES]
                rates.append(views_per_second(world, poses, size, batch, args.seconds))
            mean = sum(rates) / len(rates)
            print(
                f"render {size}x{size} batch {batch:>2}: {mean:8.1f} views/s "
                f"(min {min(rates):.1f}, max {max(rates):.1f} over {len(rates)} kitchens)"
            )


if __name__ == "__main__":
    main()
