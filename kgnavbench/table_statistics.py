"""Stage 26 — table_statistics: a table's episodes, cells, intervals and verdicts.

What Table I says is computed here, before anything is written: each job's episodes per cell
(`cell_episodes`: "column/kind" -> one EpisodeValue per episode), a row's seeds together (`RowResult`),
the table (`TableResult`), and its statistics (`table_statistics`). A cell is the mean over seeds of
each seed's episode mean, with a 95% stratified bootstrap interval over seeds and episodes
(`intervals`), the paper's number beside it. Each comparison of the spec gets, per cell and metric,
the paper's difference, ours with its interval, and a verdict (`intervals.verdict`: holds, of the
paper's size or not, reversed, higher or lower where the paper has no side, no difference beyond the
spec's margin, smaller than the paper's, cannot tell). Two tables of the same runs and episodes
(another checkpoint, or another success rule) are differenced row by row, episode by episode
(`paired_differences`).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import NamedTuple

from .intervals import (
    REPLICATES,
    Bootstrap,
    Interval,
    difference,
    joint_stratified_bootstrap,
    verdict,
)
from .metrics import EpisodeResult, spl_term
from .table_spec import (
    CELL_KEYS,
    METRICS,
    PERCENT,
    Comparison,
    Preset,
    Row,
    TableError,
    TableSpec,
)


class EpisodeValue(NamedTuple):
    """One episode as a cell's statistics need it: its stratum (kitchen/target: the bootstrap resamples
    episodes within targets) and its success and SPL term, both in percent (0 or 100; 100 * S * L /
    max(P, L))."""

    stratum: str
    success: float
    spl: float

    def value(self, metric: str) -> float:
        """The episode's value for one of METRICS."""
        return {"SPL": self.spl, "SR": self.success}[metric]


def cell_episodes(results: list[EpisodeResult]) -> dict[str, list[EpisodeValue]]:
    """One evaluation's episodes per Table I cell ("column/kind" -> values; a cell without episodes
    has an empty list). Episodes of no cell (validation kitchens) are left out."""
    cells: dict[str, list[EpisodeValue]] = {key: [] for key in CELL_KEYS}
    for r in results:
        key = f"{r.column}/{r.kind}"
        if key in cells:
            cells[key].append(
                EpisodeValue(f"{r.kitchen}/{r.target}", PERCENT * r.success, PERCENT * spl_term(r))
            )
    return cells


@dataclass
class RowResult:
    row: Row
    episodes: list[dict[str, list[EpisodeValue]]]  # per seed: "column/kind" -> its episodes
    train_runs: list[str]
    eval_runs: list[str]
    seconds: float


@dataclass
class TableResult:
    spec: TableSpec
    preset: Preset
    rows: list[RowResult]
    seconds: float
    git_revision: str
    # rows of the preset that this table leaves out (`--row`): a partial table
    left_out: tuple[str, ...] = ()
    _statistics: TableStatistics | None = field(default=None, init=False, repr=False, compare=False)

    def statistics(self) -> TableStatistics:
        """The cells' intervals and the comparisons' verdicts, computed once (the writers share them)."""
        if self._statistics is None:
            self._statistics = table_statistics(self)
        return self._statistics


@dataclass(frozen=True)
class CellStatistics:
    """One row's cell for one metric (SPL or SR), in percent."""

    seed_means: tuple[float | None, ...]  # each seed's episode mean; None: the seed has no episodes here
    episodes_per_seed: tuple[int, ...]
    bootstrap: Bootstrap | None  # None: no episodes in the cell
    interval: Interval | None  # the mean over seeds and its 95% interval


@dataclass(frozen=True)
class ComparisonStatistics:
    """One comparison in one cell for one metric: other - base, the paper's and ours, in points."""

    comparison: Comparison
    cell: str
    metric: str
    paper_base: float | None
    paper_other: float | None
    paper_difference: float | None  # None: the paper has the cell for one of the rows only, or neither
    ours: Interval | None  # None: one of the rows has no episodes in the cell
    verdict: str | None  # intervals.verdict; None where `ours` is None


@dataclass(frozen=True)
class TableStatistics:
    cells: dict[tuple[str, str, str], CellStatistics]  # (row name, "column/kind", metric)
    comparisons: list[ComparisonStatistics]


def bootstrap_seed(row_name: str, cell: str) -> tuple[int, int]:
    """Each row and cell its own random stream, named by the row's name (not its position: a row added
    or moved changes no other row's interval). Two rows' streams differ, so the bootstraps that a
    comparison differences are independent."""
    return zlib.crc32(row_name.encode()), CELL_KEYS.index(cell)


def paper_value(row: Row, cell: str, metric: str) -> float | None:
    pair = row.paper.get(cell)
    return None if pair is None else pair[METRICS.index(metric)]


def paper_difference(base: Row, other: Row, cell: str, metric: str) -> float | None:
    """The paper's other - base in a cell, as printed (2 decimals; None where it lacks either)."""
    paper_base, paper_other = paper_value(base, cell, metric), paper_value(other, cell, metric)
    if paper_base is None or paper_other is None:
        return None
    return round(paper_other - paper_base, 2) + 0.0  # + 0.0: no "-0.00"


def cell_statistics(row_result: RowResult, cell: str, reps: int = REPLICATES) -> dict[str, CellStatistics]:
    """A cell of a row, per metric: each seed's episode mean, and the mean over seeds with its 95%
    stratified bootstrap interval over the seeds that have episodes in the cell (all of them or none:
    every seed evaluates the same fixed episodes). SPL and SR come from the same resamples."""
    per_seed = [
        [(e.stratum, tuple(e.value(metric) for metric in METRICS)) for e in seed[cell]]
        for seed in row_result.episodes
    ]
    counts = tuple(len(episodes) for episodes in per_seed)
    present = [episodes for episodes in per_seed if episodes]
    boots = (
        joint_stratified_bootstrap(present, reps, bootstrap_seed(row_result.row.name, cell))
        if present
        else [None] * len(METRICS)
    )
    out = {}
    for m, (metric, boot) in enumerate(zip(METRICS, boots)):
        means = tuple(sum(values[m] for _, values in e) / len(e) if e else None for e in per_seed)
        out[metric] = CellStatistics(means, counts, boot, boot.interval() if boot else None)
    return out


def table_statistics(result: TableResult, reps: int = REPLICATES) -> TableStatistics:
    """Every row's cells and every comparison of the spec: a comparison's interval differences the two
    rows' own bootstrap replicates (independent streams), so it agrees with the cells it compares."""
    cells = {
        (r.row.name, cell, metric): statistics
        for r in result.rows
        for cell in CELL_KEYS
        for metric, statistics in cell_statistics(r, cell, reps).items()
    }
    rows = {r.row.name: r.row for r in result.rows}
    comparisons = []
    for comparison in result.spec.comparisons:
        if comparison.base not in rows or comparison.other not in rows:
            continue  # a result built without one of the rows (the spec checked the names)
        for cell in CELL_KEYS:
            for metric in METRICS:
                paper_base = paper_value(rows[comparison.base], cell, metric)
                paper_other = paper_value(rows[comparison.other], cell, metric)
                paper = paper_difference(rows[comparison.base], rows[comparison.other], cell, metric)
                base = cells[(comparison.base, cell, metric)].bootstrap
                other = cells[(comparison.other, cell, metric)].bootstrap
                ours = difference(base, other) if base is not None and other is not None else None
                comparisons.append(
                    ComparisonStatistics(
                        comparison,
                        cell,
                        metric,
                        paper_base,
                        paper_other,
                        paper,
                        ours,
                        verdict(paper, ours.low, ours.high, result.spec.protocol.margin) if ours else None,
                    )
                )
    return TableStatistics(cells, comparisons)


# what two presets must share for their tables to be of the same runs and the same fixed episodes
SAME_RUNS = (
    "frames",
    "episodes",
    "seeds",
    "row_seeds",
    "train_kitchens",
    "eval_kitchens",
    "options",
    "unseen_target_kitchens",
)


def check_same_runs(preset: Preset, base: Preset) -> None:
    """TableError unless the two presets train the same runs and evaluate the same fixed episodes."""
    differ = [f for f in SAME_RUNS if getattr(preset, f) != getattr(base, f)]
    if differ:
        raise TableError(
            f"presets {preset.name!r} and {base.name!r} differ in {', '.join(differ)}: not the same runs "
            "and episodes, so no paired difference"
        )


@dataclass(frozen=True)
class PairedDifference:
    """One row's cell for one metric, a table minus another of the same runs and episodes, in points."""

    row: str
    cell: str
    metric: str
    ours: Interval | None  # None: no episodes in the cell
    verdict: str | None  # higher, lower or cannot tell (no side is the paper's); None where `ours` is


def paired_differences(
    result: TableResult, base: TableResult, reps: int = REPLICATES
) -> list[PairedDifference]:
    """result − base for every row in both, cell and metric, where the two tables test the same runs on
    the same fixed episodes (paper-last against paper: the final weights against the rule's checkpoint;
    paper-visible against paper: one success rule against the other). Paired: each episode's value
    minus the same episode's in `base`, then the mean over seeds of each seed's mean difference with
    the 95% stratified bootstrap interval of a cell (seeds, then episodes within targets), so the
    interval is that of the change, not of two independent draws. A preset that trains other runs, or
    episodes that differ, are refused (TableError)."""
    check_same_runs(result.preset, base.preset)
    base_rows = {r.row.name: r for r in base.rows}
    out = []
    for r in result.rows:
        other = base_rows.get(r.row.name)
        if other is None:
            continue
        for cell in CELL_KEYS:
            pairs = []
            for seed, (ours, theirs) in enumerate(zip(r.episodes, other.episodes, strict=True)):
                if [e.stratum for e in ours[cell]] != [e.stratum for e in theirs[cell]]:
                    raise TableError(
                        f"row {r.row.name!r}, seed {seed}, {cell}: the two tables' episodes differ "
                        "(not the same fixed episodes): no paired difference"
                    )
                if ours[cell]:
                    pairs.append(list(zip(ours[cell], theirs[cell])))
            # SPL and SR from the same resamples, as a cell's (`cell_statistics`)
            per_seed = [
                [(a.stratum, tuple(a.value(m) - b.value(m) for m in METRICS)) for a, b in p] for p in pairs
            ]
            boots = (
                joint_stratified_bootstrap(per_seed, reps, bootstrap_seed(r.row.name, cell))
                if per_seed
                else [None] * len(METRICS)
            )
            for metric, boot in zip(METRICS, boots):
                interval = boot.interval() if boot else None
                out.append(
                    PairedDifference(
                        r.row.name, cell, metric, interval,
                        verdict(None, interval.low, interval.high, result.spec.protocol.margin)
                        if interval else None,
                    )
                )  # fmt: skip
    return out
