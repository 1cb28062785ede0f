"""How many seeds would decide Table I's comparisons? A power estimate by simulation, per cell.

For every comparison of the spec and every cell whose SR verdict is `cannot tell` in a paper preset's
table (assembled through the package's own code from the trained runs and the kept evaluations, as
`kgnavbench table --trained zoo --archive tables/episodes/paper` does), it simulates the table with S
seeds per row of the comparison and counts how often the verdict would then be decided (anything but
`cannot tell`). A simulated seed is drawn from the spread the existing seeds show: one of the row's
trained seeds, picked uniformly, with its episodes resampled within each target (so no two simulated
seeds are copies). The simulated cell's interval and verdict are the table's own: the stratified
bootstrap over seeds, then episodes within targets (`intervals.stratified_bootstrap`, fewer replicates
than the table's 2000 for speed), the difference of the two rows' independent replicates
(`intervals.difference`) and `intervals.verdict` at the spec's margin. This assumes the seeds to come
look like the seeds at hand; with 3 seeds, that spread is itself uncertain, so the figures are a
guide to where seeds decide, not a promise.

It prints, per comparison and undecided cell, the probability of a decided verdict with 6, 9 and 12
seeds per row (a row never below the seeds it has), the verdict most often reached, and the fewest of
those seeds that decide it in 80% of the simulated tables; then, per row, the expected number of
undecided cells three more seeds of that row would decide (the other row of each comparison at the
seeds it has), and per core-hour of its training (the `seconds` of its runs' finished.json in zoo/).

Run: .venv/bin/python benchmarks/seed_power.py [--preset paper-last] [--sims 20] [--reps 400]
(a few minutes to assemble the table from the archive, then about a second per simulated cell)
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import zlib
from collections import Counter
from pathlib import Path

import numpy as np

from kgnavbench.intervals import CANNOT_TELL, difference, stratified_bootstrap, verdict
from kgnavbench.jobs import Sources
from kgnavbench.table import run_table
from kgnavbench.table_spec import CELL_TITLES, load_spec
from kgnavbench.table_statistics import paper_difference

ROOT = Path(__file__).resolve().parents[1]
SEEDS = (6, 9, 12)
MORE = 3  # the seeds added to one row in the per-row estimate
POWER = 0.8  # a cell is "decided from S seeds" when that share of the simulated tables decide it


def resampled(episodes: list[tuple[str, float]], rng: np.random.Generator) -> list[tuple[str, float]]:
    """One simulated seed from a trained one: its episodes drawn with replacement within each target."""
    by_target: dict[str, list[float]] = {}
    for stratum, value in episodes:
        by_target.setdefault(stratum, []).append(value)
    out = []
    for stratum, values in by_target.items():
        out += [(stratum, values[i]) for i in rng.integers(0, len(values), len(values))]
    return out


def simulated_row(seeds: list[list[tuple[str, float]]], n: int, rng) -> list[list[tuple[str, float]]]:
    """n seeds: the trained ones as they are, then simulated ones drawn from them."""
    extra = [resampled(seeds[rng.integers(0, len(seeds))], rng) for _ in range(max(0, n - len(seeds)))]
    return list(seeds[:n]) + extra


def decided(base, other, n_base, n_other, paper, margin, sims, reps, rng) -> tuple[float, str]:
    """The share of simulations whose verdict is decided, and the verdict reached most often."""
    verdicts = []
    for _ in range(sims):
        b = stratified_bootstrap(simulated_row(base, n_base, rng), reps, int(rng.integers(2**31)))
        o = stratified_bootstrap(simulated_row(other, n_other, rng), reps, int(rng.integers(2**31)))
        ours = difference(b, o)
        verdicts.append(verdict(paper, ours.low, ours.high, margin))
    share = sum(v != CANNOT_TELL for v in verdicts) / sims
    return share, Counter(verdicts).most_common(1)[0][0]


def core_hours(row_name: str) -> float:
    """The mean training core-hours of a row's runs in zoo/ (their finished.json's seconds), the runs
    found by the zoo's own listing (zoo/README.md, written by `kgnavbench ship`)."""
    hours = []
    for line in (ROOT / "zoo" / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 7 and cells[1] == row_name and cells[0].startswith("`"):
            finished = ROOT / "zoo" / cells[0].strip("`") / "finished.json"
            hours.append(json.loads(finished.read_text())["seconds"] / 3600)
    return float(np.mean(hours)) if hours else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper-last")
    ap.add_argument("--sims", type=int, default=20, help="simulated tables per cell and seed count")
    ap.add_argument("--reps", type=int, default=400, help="bootstrap replicates per simulated interval")
    ap.add_argument(
        "--runs", type=Path, help="runs folder to unpack the evaluations into (default: a temporary one)"
    )
    args = ap.parse_args()
    spec = load_spec()
    margin = spec.protocol.margin
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        sources = Sources(ROOT / "zoo", False, ROOT / "tables" / "episodes" / "paper")
        quiet = {"progress": lambda line: None, "workers": 2, "sources": sources}
        result = run_table(spec, args.preset, args.runs or Path(tmp), **quiet)
    print(
        f"preset {args.preset!r}: assembled in {time.perf_counter() - start:.0f} s; margin {margin:g} points"
    )
    rows = {r.row.name: r for r in result.rows}
    open_cells = [s for s in result.statistics().comparisons if s.metric == "SR" and s.verdict == CANNOT_TELL]
    print(
        f"{len(open_cells)} SR cells read 'cannot tell'; P(decided) with S seeds per row of the comparison:"
    )
    gained: Counter = Counter()
    for s in open_cells:
        base, other = rows[s.comparison.base], rows[s.comparison.other]
        per = [[[(e.stratum, e.success) for e in seed[s.cell]] for seed in r.episodes] for r in (base, other)]
        paper = paper_difference(base.row, other.row, s.cell, "SR")
        rng = np.random.default_rng(zlib.crc32(f"{s.comparison}{s.cell}".encode()))
        line, enough = [], None
        have = [len(seeds) for seeds in per]  # the seeds each row has: never simulated below them
        for n in SEEDS:
            share, modal = decided(
                *per, max(n, have[0]), max(n, have[1]), paper, margin, args.sims, args.reps, rng
            )
            line.append(f"S={n}: {share:.0%} ({modal})")
            enough = enough or (n if share >= POWER else None)
        # one row with MORE seeds, the other at its own: what adding seeds to that row alone decides
        for who, (nb, no) in (
            (s.comparison.base, (have[0] + MORE, have[1])),
            (s.comparison.other, (have[0], have[1] + MORE)),
        ):
            share, _ = decided(*per, nb, no, paper, margin, args.sims, args.reps, rng)
            gained[who] += share
        print(
            f"  {s.comparison.other} − {s.comparison.base}, {CELL_TITLES[s.cell]}: now "
            f"{s.ours.estimate:+.1f} [{s.ours.low:+.1f}, {s.ours.high:+.1f}] "
            f"({have[0]} and {have[1]} seeds); "
            + "; ".join(line)
            + f"; decided in {POWER:.0%} of tables from {enough or f'more than {SEEDS[-1]}'} seeds"
        )
    print(
        f"expected undecided cells decided by {MORE} more seeds of one row "
        "(the other row of each comparison at its own):"
    )
    for name, cells in gained.most_common():
        hours = core_hours(name)
        print(
            f"  {name}: {cells:.1f} cells for {MORE} more runs, {MORE * hours:.1f} core-hours of training: "
            f"{cells / (MORE * hours):.2f} cells per core-hour"
        )
    print(
        f"{time.perf_counter() - start:.0f} s in all ({args.sims} simulations of {args.reps} replicates each)"
    )


if __name__ == "__main__":
    main()
