"""Stage 32 — table_paired: two presets' tables compared episode by episode (`table --against`).

The same rows of two presets, evaluated on the same fixed episodes, give per cell and metric a
paired difference (`table_statistics.paired_differences`); this stage writes them as markdown and
CSV beside the two tables, with the verdicts the ablation check uses.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from .evaluate import SUCCESS_RULE_TEXT
from .intervals import (
    CANNOT_TELL,
    HIGHER,
    LOWER,
    REPLICATES,
    no_difference,
)
from .jobs import (
    checkpoint_rule,
)
from .table_files import (
    NONE,
    Written,
    interval_text,
    markdown_table,
    number_text,
    verdict_counts,
    write_files,
)
from .table_spec import (
    CELL_KEYS,
    CELL_TITLES,
    METRICS,
)
from .table_statistics import PairedDifference, TableResult


def paired_intro(result: TableResult, base: TableResult) -> str:
    """What a paired-difference table holds (its caption's first part)."""
    return (
        f"Paired difference: preset {result.preset.name!r} ({_tested(result)}) − preset "
        f"{base.preset.name!r} ({_tested(base)}), the same runs on the same fixed episodes, in percentage "
        "points: per row and cell, the mean over seeds of each seed's mean per-episode difference, with "
        f"the 95% stratified bootstrap interval over seeds and episodes ({REPLICATES} replicates); at a "
        f"margin of {result.spec.protocol.margin:g} points, higher or lower: the interval lies above or "
        f"below 0; {no_difference(result.spec.protocol.margin)}: it lies within "
        f"±{result.spec.protocol.margin:g}; cannot tell: neither. Each verdict reads one 95% interval, so "
        "among many cells a few are wrong by chance. '–': no episodes."
    )


def _tested(result: TableResult) -> str:
    """'best.pt: the best validation SR; success: Stop at the destination': what a preset tests."""
    last = checkpoint_rule(result.spec, result.preset) == "last"
    checkpoint = "last.pt: the final weights" if last else "best.pt: the best validation SR"
    rule = result.preset.score_rule or result.spec.protocol.success_rule
    return f"{checkpoint}; success: {SUCCESS_RULE_TEXT[rule]}"


def paired_verdict_counts(diffs: list[PairedDifference], margin: float) -> str:
    """'SPL: higher 3, lower 1, no difference beyond 3 2, cannot tell 6; SR: ...' (no side is the paper's)."""
    return verdict_counts(diffs, (HIGHER, LOWER, no_difference(margin), CANNOT_TELL))


def to_paired_markdown(result: TableResult, base: TableResult, diffs: list[PairedDifference]) -> str:
    """One table per metric: a line per row, a column per cell, each 'difference [interval] verdict'."""
    by_key = {(d.row, d.cell, d.metric): d for d in diffs}
    rows = list(dict.fromkeys(d.row for d in diffs))
    lines = [f"**{paired_intro(result, base)} Git {result.git_revision}.**"]
    for metric in METRICS:
        head = [f"row ({metric})"] + [CELL_TITLES[cell] for cell in CELL_KEYS]
        body = []
        for row in rows:
            cells = []
            for cell in CELL_KEYS:
                d = by_key[(row, cell, metric)]
                cells.append(NONE if d.ours is None else f"{interval_text(d.ours, signed=True)} {d.verdict}")
            body.append([row, *cells])
        lines += ["", *markdown_table(head, body, numeric=set(range(1, len(head))))]
    lines += ["", f"Verdicts: {paired_verdict_counts(diffs, result.spec.protocol.margin)}."]
    return "\n".join(lines) + "\n"


def to_paired_csv(result: TableResult, base: TableResult, diffs: list[PairedDifference]) -> str:
    """Tidy: one line per row, cell and metric: the difference with its 95% interval and the verdict."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow([f"# {paired_intro(result, base)} Git {result.git_revision}."])
    writer.writerow(["row", "column", "kind", "metric", "difference", "ci_low", "ci_high", "verdict"])
    for d in diffs:
        column, _, kind = d.cell.partition("/")
        i = d.ours
        writer.writerow(
            [d.row, column, kind, d.metric, number_text(i.estimate if i else None)]
            + [number_text(i.low if i else None), number_text(i.high if i else None), d.verdict or ""]
        )
    return out.getvalue()


def write_paired(
    result: TableResult, base: TableResult, diffs: list[PairedDifference], out_dir: Path | str
) -> Written:
    """table1-<preset>-against-<base>.md and .csv (`-partial` after the preset's name as `write_table`)."""
    stem = f"table1-{result.preset.name}{'-partial' if result.left_out else ''}-against-{base.preset.name}"
    return write_files(
        out_dir,
        (
            (f"{stem}.md", to_paired_markdown(result, base, diffs)),
            (f"{stem}.csv", to_paired_csv(result, base, diffs)),
        ),
    )
