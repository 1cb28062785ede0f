"""How much TSE relabels: a row of a Table I preset trained for a short while, as `kgnavbench train --preset`
trains it, with counters on the package's own TSE functions; printed per million frames.

    python benchmarks/tse_relabels.py                                   # +TSE under paper and paper-protocol
    python benchmarks/tse_relabels.py --presets paper-protocol --frames 2000000 --set stop_ends_from=0

TSE relabels the sub-target windows of the episodes that end in a rollout (`losses.SubtargetSampler`:
up to `tse_subtargets` steps per episode that reached a state showing a sub-target object, each with at
most `tse_window` steps before it), and each update takes up to `tse_batch` of them
(`learning.relabelled_windows`). So the relabels per frame depend on how often episodes end: 200-action
episodes end 25 times as often as 5000-action ones. Counters wrap `SubtargetSampler.finish` (episodes
ended, windows sampled, windows the window's length cut: as long as `tse_window`) and
`relabelled_windows` as the trainer calls it (windows offered and taken per update, relabelled steps).
Runs train into a temporary folder, seed 0, with `--frames` as the run's frames (so a start curriculum
scales with them, as it does there); nothing is written elsewhere.
"""

from __future__ import annotations

import argparse
import tempfile
from collections import Counter
from pathlib import Path

from kgnavbench import losses, runs, train
from kgnavbench.plugins import load_plugin, parse_options
from kgnavbench.table_spec import SPEC_FILE, load_spec


def count(method: str, options: dict, frames: int, kitchens, directory: Path) -> tuple[Counter, int]:
    """Train the run for `frames` with counters on TSE's functions: (counts, frames trained)."""
    plugin = load_plugin(method)
    config = plugin.config(options)
    run = runs.Run(directory, method, frames, 0, runs.training_kitchens(kitchens), lambda line: None, "cpu")
    counts: Counter = Counter()
    finish, relabelled = losses.SubtargetSampler.finish, train.relabelled_windows

    def counted_finish(self, idx, next_tick):
        windows = finish(self, idx, next_tick)
        counts["episodes ended"] += len(idx)
        counts["windows sampled"] += len(windows)
        counts["windows cut by tse_window"] += sum(len(w.actions) >= self.window for w in windows)
        return windows

    def counted_relabelled(windows, opts, rng):
        seqs = relabelled(windows, opts, rng)
        counts["updates"] += 1
        counts["windows offered"] += len(windows)
        if seqs is not None:
            counts["updates with relabels"] += 1
            counts["relabelled episodes"] += len(seqs.goal)
            counts["relabelled steps"] += int(seqs.mask.sum())
        return seqs

    losses.SubtargetSampler.finish, train.relabelled_windows = counted_finish, counted_relabelled
    try:
        train.learn(run, config, plugin.module.model_config(config), rl=True)
    finally:
        losses.SubtargetSampler.finish, train.relabelled_windows = finish, relabelled
    done = train.read_metrics_rows(directory / "metrics.csv", frames * 2)
    return counts, int(done[-1]["frames"]) if done else frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--row", default="+TSE", help="a row of the spec with tse=true")
    parser.add_argument("--presets", default="paper,paper-protocol", help="comma-separated")
    parser.add_argument("--spec", default=str(SPEC_FILE))
    parser.add_argument("--frames", type=int, default=1_000_000, help="the run's frames (default 1M)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="an option over the row's"
    )
    args = parser.parse_args()
    spec = load_spec(args.spec)
    row = {r.name: r for r in spec.rows}[args.row]
    for name in args.presets.split(","):
        preset = spec.preset(name)
        options = {**preset.options, **row.options, **parse_options(args.set)}
        with tempfile.TemporaryDirectory() as folder:
            counts, frames = count(row.method, options, args.frames, preset.train_kitchens, Path(folder))
        per = 1e6 / frames
        extra = f" with {' '.join(args.set)}" if args.set else ""
        print(f"{args.row} under {name}{extra}: {frames:,} frames, seed 0 (per million frames)")
        for key in ("episodes ended", "windows sampled", "windows cut by tse_window", "windows offered",
                    "relabelled episodes", "relabelled steps"):  # fmt: skip
            print(f"  {key:28s} {counts[key] * per:10,.0f}")
        share = counts["updates with relabels"] / max(counts["updates"], 1)
        print(f"  {'updates with relabels':28s} {100 * share:9.1f} %")


if __name__ == "__main__":
    main()
