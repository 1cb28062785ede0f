"""Does a learner master a small task? SR on the fixed episodes of N seen targets of one kitchen after
a short run, for the A2C trainer alone and with DAgger's shortest-path teacher.

    python benchmarks/small_task.py                                   # FloorPlan25, 2 targets, 300k and 1M
    python benchmarks/small_task.py --kitchen FloorPlan1 --frames 600k --variants a2c

Each variant trains lstm_a3c (widths 64, 32 agents on the kitchen's first `--targets` seen targets,
the start-distance curriculum over half the run, 100-action training episodes that Stop ends), then
runs 20 fixed episodes per target at Table I's seen cap (100 actions, Stop at the destination) and
prints the SR per target and overall, with the seconds it took. tests/test_train.py holds the
variant with the teacher to at least 80%; this measures what A2C alone does at the same budget.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from kgnavbench import agent, models, runs, train
from kgnavbench.arguments import frames as frame_count

VARIANTS = {
    "a2c": {},
    "a2c+dagger": {"il": True, "il_expert": "dagger"},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kitchen", default="FloorPlan25", help="a training kitchen (default: the smallest)")
    parser.add_argument("--targets", type=int, default=2, help="its first N seen targets")
    parser.add_argument("--frames", default="300k,1M", help="run lengths, comma-separated")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"of {', '.join(VARIANTS)}")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = models.ModelConfig(hidden=64, lstm=64)
    for variant in args.variants.split(","):
        for frames in (frame_count(f) for f in args.frames.split(",")):
            options = runs.TrainOptions(
                agents_per_kitchen=32,
                targets_per_kitchen=args.targets,
                episode_cap=100,
                stop_ends_from=0,
                start_curriculum=0.5,
                threads=1,
                log_every=100_000,
                val_every=10**9,
                val_kitchens=1,
                val_episodes=1,
                **VARIANTS[variant],
            )
            start = time.perf_counter()
            with tempfile.TemporaryDirectory() as tmp:
                run = runs.Run(Path(tmp), "lstm_a3c", frames, args.seed, (args.kitchen,), lambda line: None)
                train.learn(run, options, config)
                trainer = train.Trainer(run, options, config, True)
                trainer.load_state_dict(runs.load_checkpoint(Path(tmp) / "last.pt"))
            space = trainer.space
            cells = []
            for r in np.unique(trainer.actors.nav.assigned):
                starts = np.array(space.fixed_starts[r][:20])
                sr, _, _ = agent.run_episodes(trainer.model, space, np.repeat(r, len(starts)), starts, 100, 1)
                cells.append((space.target_ids[r].split("|")[0], sr))
            overall = float(np.mean([sr for _, sr in cells]))
            per_target = ", ".join(f"{name} {sr:.0f}%" for name, sr in cells)
            print(
                f"{variant:11s} {args.kitchen}, {args.targets} targets, {frames:>9,} frames: "
                f"SR {overall:5.1f}% "
                f"({per_target}) in {time.perf_counter() - start:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
