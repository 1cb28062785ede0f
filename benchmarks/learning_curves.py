"""Learning curves of Table I's learned LSTM rows: validation SR (and SPL) every `--every` frames.

Trains Table I's rows LSTM A3C, +IL, +TSE, +IL+TSE, +KG and +KG+Attention, each with its options
from tables/table1.toml, on the 20 training kitchens (or the given ones) into RUNS/train/ (resumable;
a finished run is reused), then prints one line per run with its
validation SR and SPL (%) at every validation, on the first 5 validation kitchens and `--episodes`
fixed episodes per target, cap 1000. With `--seen`, it also evaluates each run's best-validation
checkpoint (`best.pt`, Table I's rule) and its final weights (`last.pt`) on the training kitchens'
seen targets (2 fixed episodes per target, cap 100), as `kgnavbench eval --run DIR --checkpoint
best|last --split train --episodes 2` does, and prints their seen/seen SR. Rows run one after another:
never beside another benchmark.

    python benchmarks/learning_curves.py --frames 10M --every 1M --agents 4
    python benchmarks/learning_curves.py --frames 10M --every 1M --agents 4 --rows +KG+Attention --seen
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

from kgnavbench.arguments import frames as frame_count  # the CLI's parser: 10M, 500k, 2_000_000
from kgnavbench.evaluate import EvalConfig, evaluate
from kgnavbench.runs import train_method
from kgnavbench.table_spec import load_spec

ROWS = [
    (row.name, row.method, row.options)
    for row in load_spec().rows
    if row.method in ("lstm_a3c", "kg_attention")
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=frame_count, default="10M", help="frames per run (10M, 500k)")
    parser.add_argument("--every", type=frame_count, default="1M", help="frames between validations")
    parser.add_argument("--agents", default="4", help="agents per training kitchen")
    parser.add_argument("--episodes", default="2", help="fixed episodes per validation target")
    parser.add_argument("--rows", default="", help="only these rows, e.g. '+IL,+KG'")
    parser.add_argument("--kitchens", default="", help="training kitchens (default: all 20)")
    parser.add_argument("--runs", type=Path, default=Path("runs"))
    parser.add_argument(
        "--seen", action="store_true", help="also the seen/seen SR of each run's best.pt and last.pt"
    )
    args = parser.parse_args()
    frames, every = args.frames, args.every
    rows = [r for r in ROWS if not args.rows or r[0] in args.rows.split(",")]
    kitchens = tuple(k for k in args.kitchens.split(",") if k)
    common = {
        "agents_per_kitchen": args.agents,
        "val_every": str(every),
        "log_every": str(min(every, 1_000_000)),
        "val_episodes": args.episodes,
    }
    curves = []
    for name, method, options in rows:
        start = time.perf_counter()
        directory = train_method(
            method, {**common, **options}, frames, 0, kitchens, args.runs, progress=lambda line: None
        )
        with open(directory / "metrics.csv", newline="") as f:
            points = [r for r in csv.DictReader(f) if r["val_sr"]]
        line = "  ".join(f"{int(r['frames']) / 1e6:.1f}M {float(r['val_sr']):5.1f}" for r in points)
        curves.append((name, line, points))
        seconds = time.perf_counter() - start
        print(f"{name:14s} validation SR (%) at frames: {line}   ({seconds:.0f} s)", flush=True)
        if args.seen:
            for which in ("best", "last"):
                seen = seen_sr(method, {**common, **options}, directory, which, kitchens, args.runs)
                print(f"{name:14s} {seen}", flush=True)
    print(f"\n{frames:,} frames per run, {args.agents} agents per kitchen; SR / SPL (%) per validation")
    for name, _, points in curves:
        cells = " | ".join(f"{float(r['val_sr']):.1f} / {float(r['val_spl']):.1f}" for r in points)
        print(f"| {name} | {cells} |")


def seen_sr(method: str, options: dict, directory: Path, which: str, kitchens, runs: Path) -> str:
    """The seen/seen SR and SPL of one of a run's checkpoints on its training kitchens' seen targets."""
    config = EvalConfig(
        method=method,
        options=tuple(sorted(options.items())),
        split="train",
        kitchens=kitchens,
        episodes_per_target=2,
        run=str(directory),
        checkpoint=which,
    )
    run = evaluate(config, runs, progress=lambda line: None)
    cells = []
    for kind in ("static", "actionable"):
        m = run.summary[("seen_seen", kind)]
        cells.append(f"{kind} SR {m.sr:.2f} SPL {m.spl:.2f} ({m.episodes} episodes)")
    return f"seen/seen, {which}.pt: " + ", ".join(cells)


if __name__ == "__main__":
    main()
