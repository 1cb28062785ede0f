"""Learning curves of Table I's learned rows under a preset's schedule: the SR of weight snapshots kept
every `--every` frames, on the fixed episodes at Table I's caps and rule.

For each row (default +IL+TSE and +KG+Attention) and seed it trains the row under the preset's `set`
from tables/table1.toml (default: the paper preset, 40M frames), with `--set` overrides (a candidate
schedule) and snapshots kept every `--every` frames (`keep_every`), into RUNS/train/ (resumable; a
finished run is reused: with the paper preset's own options these are the table's runs). Then it
evaluates every snapshot, and the run's best.pt (Table I's checkpoint rule) and last.pt, as
`kgnavbench eval --run DIR --checkpoint frames-N --split train --episodes E` does (evaluations are
resumed and reused too): seen kitchens with seen targets (static and actionable, cap 100) and with
unseen targets (static, cap 1000), and the 5 test kitchens (unseen kitchens, static, cap 1000: what
the validation kitchens stand in for when Table I's rule picks a checkpoint). The validation SR is the
run's own at that snapshot (metrics.csv).

It writes OUT.csv (columns row, seed, frames, seen_seen_static_sr, seen_seen_actionable_sr,
seen_unseen_static_sr, val_sr, checkpoint, unseen_static_sr) and OUT.png (the curves, the paper's 40M
numbers marked), and prints the table. Rows run one after another in one process: to use two cores,
run two processes with different `--rows` and the same `--runs`, then once more with all rows (it
only evaluates and draws). Never beside a speed benchmark.

    python benchmarks/learning_curves.py --runs ~/kgnav-runs --rows +IL+TSE          # one core
    python benchmarks/learning_curves.py --runs ~/kgnav-runs --rows +KG+Attention    # the other
    python benchmarks/learning_curves.py --runs ~/kgnav-runs --out docs/figures/learning_curves_paper
    python benchmarks/learning_curves.py --runs ~/kgnav-runs --set start_curriculum=0.05 \\
        --out docs/figures/learning_curves_short_curriculum        # a candidate schedule
    python benchmarks/learning_curves.py --preset smoke --frames 2000 --every 1000 --episodes 1 \\
        --runs /tmp/lc --out /tmp/lc/curves                       # seconds: the script itself
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import torch

from kgnavbench.arguments import frames as frame_count  # the CLI's parser: 10M, 500k, 2_000_000
from kgnavbench.checkpoints import snapshot_frames, validation_at
from kgnavbench.evaluate import EvalConfig, evaluate
from kgnavbench.plots import curves_figure
from kgnavbench.runs import load_checkpoint, train_method
from kgnavbench.table_spec import TableError, load_spec

COLUMNS = (
    "row",
    "seed",
    "frames",
    "seen_seen_static_sr",
    "seen_seen_actionable_sr",
    "seen_unseen_static_sr",
    "val_sr",
    "checkpoint",  # frames-N (a snapshot), best (Table I's rule) or last
    "unseen_static_sr",  # the 5 test kitchens: what the validation kitchens stand in for
)
CELLS = {  # column of the CSV: (split, Table I column, kind)
    "seen_seen_static_sr": ("train", "seen_seen", "static"),
    "seen_seen_actionable_sr": ("train", "seen_seen", "actionable"),
    "seen_unseen_static_sr": ("train", "seen_unseen", "static"),
    "unseen_static_sr": ("test", "unseen_kitchens", "static"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--preset", default="paper", help="the table spec's preset whose `set` is the schedule"
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="K=V", help="override a training option"
    )
    parser.add_argument("--rows", default="+IL+TSE,+KG+Attention", help="Table I rows, comma-separated")
    parser.add_argument("--seeds", default="0", help="training seeds, comma-separated")
    parser.add_argument(
        "--frames", type=frame_count, default=None, help="frames per run (default: the preset's)"
    )
    parser.add_argument(
        "--every",
        type=frame_count,
        default=None,
        help="frames between snapshots (default: the preset's keep_every, else 5M)",
    )
    parser.add_argument("--episodes", type=int, default=5, help="fixed episodes per target (of 100)")
    parser.add_argument("--runs", type=Path, default=Path("runs"))
    parser.add_argument("--out", type=Path, default=None, help="OUT.csv and OUT.png (default: print only)")
    args = parser.parse_args()
    torch.set_num_threads(1)  # one job per core, as the table's jobs (training: the preset's threads)
    try:
        spec = load_spec()
        preset = spec.preset(args.preset)
    except TableError as e:
        parser.error(str(e))
    rows = {r.name: r for r in spec.rows}
    names = [n for n in args.rows.split(",") if n]
    unknown = [n for n in names if n not in rows]
    if unknown:
        parser.error(f"unknown rows {unknown}; the spec has {', '.join(rows)}")
    overrides = dict(kv.split("=", 1) for kv in args.set)
    if args.every:
        overrides["keep_every"] = str(args.every)
    frames = args.frames or preset.frames
    kitchens = tuple(preset.train_kitchens)
    points = []
    for name in names:
        row = rows[name]
        for seed in (int(s) for s in args.seeds.split(",")):
            # the table's own options (its runs are reused), snapshots as asked, the candidate's changes
            options = {**preset.options, **row.options, **overrides}
            options.setdefault("keep_every", "5000000")
            start = time.perf_counter()
            directory = train_method(row.method, options, frames, seed, kitchens, args.runs, progress=print)
            print(
                f"{name} (seed {seed}): trained in {time.perf_counter() - start:.0f} s: {directory}",
                flush=True,
            )
            points += curve(name, row.method, options, seed, directory, args.episodes, args.runs, kitchens)
    print(" | ".join(COLUMNS))
    for p in points:
        print(" | ".join(str(p[c]) for c in COLUMNS))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out.with_suffix(".csv"), "w", newline="") as f:
            writer = csv.DictWriter(f, COLUMNS)
            writer.writeheader()
            writer.writerows(points)
        figure(
            points, {n: rows[n].paper for n in names}, args.out.with_suffix(".png"), args.preset, overrides
        )
        print(f"wrote {args.out.with_suffix('.csv')} and {args.out.with_suffix('.png')}")


def curve(name, method, options, seed, directory: Path, episodes: int, runs: Path, kitchens=()) -> list[dict]:
    """One point per snapshot (then best and last) of a trained run."""
    # the run read as `kgnavbench checkpoints` reads it: its snapshots, validation SR and checkpoints' frames
    val = {frames: f"{sr:.2f}" for frames, (sr, _episodes) in validation_at(directory).items()}
    snapshots = [(frames, f"frames-{frames}") for frames in snapshot_frames(directory)]
    best, last = (int(load_checkpoint(directory / f"{which}.pt")["frames"]) for which in ("best", "last"))
    checkpoints = [*snapshots, (best, "best"), (last, "last")]
    out = []
    for at, which in checkpoints:
        start = time.perf_counter()
        summaries = {}
        for split in ("train", "test"):
            config = EvalConfig(
                method=method,
                options=tuple(sorted(options.items())),
                split=split,
                # the run's training kitchens (empty: all 20); the test split's 5 kitchens
                kitchens=kitchens if split == "train" else (),
                episodes_per_target=episodes,
                run=str(directory),
                checkpoint=which,
            )
            summaries[split] = evaluate(config, runs, progress=lambda line: None).summary
        point = {"row": name, "seed": seed, "frames": at, "checkpoint": which}
        for column, (split, *cell) in CELLS.items():
            m = summaries[split].get(tuple(cell))
            point[column] = f"{m.sr:.2f}" if m is not None and m.episodes else ""
        point["val_sr"] = val.get(at, "")
        print(f"{name} (seed {seed}) {which} at {at:,} frames: {point} ({time.perf_counter() - start:.0f} s)")
        out.append(point)
    return out


def figure(points: list[dict], paper: dict, path: Path, preset: str, overrides: dict) -> None:
    """The snapshots' SR over frames (seen/seen, seen/unseen and unseen kitchens, static; the
    validation SR), one line per row, seed and column; the paper's 40M numbers marked in the same
    colour (hollow squares at 40M)."""
    series, marks = {}, {}
    panels = (("seen_seen_static_sr", "seen/seen static", "seen_seen/static"),
              ("seen_unseen_static_sr", "seen/unseen static", "seen_unseen/static"),
              ("unseen_static_sr", "unseen kitchens static", "unseen_kitchens/static"),
              ("val_sr", "validation", None))  # fmt: skip
    for column, label, cell in panels:
        for p in points:
            if not p["checkpoint"].startswith("frames-"):
                continue
            key = f"{p['row']} s{p['seed']}, {label}"
            xs, ys = series.setdefault(key, ([], []))
            xs.append(p["frames"] / 1e6)
            ys.append(float(p[column]) if p[column] != "" else math.nan)
            if cell is not None and cell in paper.get(p["row"], {}):
                marks[key] = [(40.0, paper[p["row"]][cell][1])]
    title = f"Learning curves, {preset} preset" + (
        " with " + ", ".join(f"{k}={v}" for k, v in overrides.items()) if overrides else ""
    )
    curves_figure(
        series,
        path,
        title + "; squares: the paper at 40M",
        "frames (millions)",
        "SR (%), Table I's caps and rule",
        x_include=(0.0, 40.0),
        y_include=(0.0, 100.0),
        marks=marks,
    )


if __name__ == "__main__":
    main()
