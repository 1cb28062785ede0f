"""Agent-steps per second of a learned policy's evaluation: `evaluate.evaluate` end to end.

    python benchmarks/eval_speed.py --run runs/train/lstm_a3c-...          # a trained run
    python benchmarks/eval_speed.py --run runs/train/kg_attention-... --episodes 20
    python benchmarks/eval_speed.py                                        # trains a tiny run first
    python benchmarks/eval_speed.py --run DIR --profile eval.prof          # and where the time goes
    python benchmarks/eval_speed.py --run DIR --threads 1                  # torch on one thread

Exactly what `kgnavbench eval --method M --run DIR` does (the env, the plugin interface, the policy's
act() over every episode of a kitchen at once, the results file), into a temporary runs folder, so
nothing is resumed and nothing is written elsewhere. Per kitchen: the episodes' agent-steps (episode
lengths, Stop counted) over the seconds from the start of that kitchen to its results file; overall:
all agent-steps over the whole evaluation. Without --run it first trains `--method` for `--frames`
frames on FloorPlan1 (7 agents, validated on one kitchen) into the temporary folder: an early
checkpoint, whose agents rarely stop where they should, so many episodes run to their caps (100 seen,
1000 unseen). On a machine shared with other work, compare figures measured back to back; torch's
threads (default: one per core) wait on each other when the cores are busy, `--threads 1` avoids that.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import tempfile
import time
from pathlib import Path

import torch

from kgnavbench.evaluate import EvalConfig, evaluate
from kgnavbench.plugins import parse_options
from kgnavbench.runs import train_method


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", default="", help="a training run directory (default: train a tiny one)")
    ap.add_argument("--method", default="", help="the run's method (default: its config.json's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="plugin options")
    ap.add_argument("--checkpoint", default="best", choices=("best", "last"))
    ap.add_argument(
        "--kitchens",
        default="FloorPlan1,FloorPlan2,FloorPlan27",
        help="kitchens of Table I (training or test)",
    )
    ap.add_argument("--episodes", type=int, default=20, help="fixed episodes per target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=5_000, help="frames of the tiny run (without --run)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's own choice)")
    ap.add_argument("--profile", default="", help="write a cProfile of the evaluation here, print its top")
    args = ap.parse_args()
    options = parse_options(args.set)
    if args.threads:
        torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory(prefix="eval_speed-") as tmp:
        run_dir = Path(args.run) if args.run else None
        method = args.method
        if run_dir is None:
            method = method or "lstm_a3c"
            t0 = time.perf_counter()
            run_dir = train_method(
                method,
                {**options, "agents_per_kitchen": "7", "val_kitchens": "1", "val_episodes": "1"},
                frames=args.frames,
                kitchens=("FloorPlan1",),
                runs_dir=tmp,
                progress=lambda line: None,
            )
            print(f"trained a tiny {method} run ({args.frames:,} frames) in {time.perf_counter() - t0:.1f} s")
        elif not method:
            method = json.loads((run_dir / "config.json").read_text())["method"]
        config = EvalConfig(
            method=method,
            options=tuple(sorted(options.items())),
            kitchens=tuple(args.kitchens.split(",")),
            episodes_per_target=args.episodes,
            seed=args.seed,
            run=str(run_dir),
            checkpoint=args.checkpoint,
        )
        marks = []  # evaluate reports each kitchen as it finishes: the time of each report
        profiler = cProfile.Profile() if args.profile else None
        start = time.perf_counter()
        if profiler:
            profiler.enable()
        run = evaluate(config, Path(tmp) / "eval", progress=lambda line: marks.append(time.perf_counter()))
        if profiler:
            profiler.disable()
        total = time.perf_counter() - start
    where = args.run or f"a tiny run of {args.frames:,} frames"
    print(
        f"{' '.join([method, *args.set])}: {where}, checkpoint {args.checkpoint}.pt, "
        f"{args.episodes} episodes per target, {torch.get_num_threads()} torch threads"
    )
    previous = start
    for kitchen, mark in zip(config.kitchens, marks):
        results = [r for r in run.results if r.kitchen == kitchen]
        steps = sum(r.episode_length for r in results)
        seconds = mark - previous
        previous = mark
        print(
            f"{kitchen:12s} {len(results):5d} episodes {steps:9,d} agent-steps in {seconds:7.2f} s "
            f"{steps / seconds:9,.0f} agent-steps/s"
        )
    steps = sum(r.episode_length for r in run.results)
    print(
        f"overall      {len(run.results):5d} episodes {steps:9,d} agent-steps in {total:7.2f} s "
        f"{steps / total:9,.0f} agent-steps/s"
    )
    if profiler:
        profiler.dump_stats(args.profile)
        pstats.Stats(args.profile).sort_stats("tottime").print_stats(25)


if __name__ == "__main__":
    main()
