"""Stage 30 — table: the paper's Table I from a table spec (`tables/table1.toml`), assembled and written.

The spec (kgnavbench/table_spec.py) names the protocol, the presets, the rows and the comparisons
the paper draws between rows. `run_table` runs every row and seed (`jobs`): train unless a finished
run with the same config exists (an unfinished one resumes), take the checkpoint with the best
validation SR, evaluate it on the fixed episodes (per-episode JSON lines in the eval run). It then
assembles the rows (`table_statistics`) and `write_table` writes the table as markdown, CSV and LaTeX.
Everything it runs is a resumable run directory, so a killed `make table` continues where it stopped.

Table I has five cells per row, each SPL and SR in percent (`CELLS`): static targets in seen kitchens
with seen targets, seen kitchens with unseen targets and unseen kitchens; actionable targets in seen
kitchens with seen targets and unseen kitchens (no actionable target of a training kitchen is unseen).
A cell is the mean over seeds with its 95% interval, the paper's number beside it; "–" where there are
no episodes or the paper has none (FF A3C in unseen kitchens). Under the table, each comparison of the
spec gets, per cell and metric, the paper's difference, ours with its interval, and a verdict.
"""

from __future__ import annotations

import csv
import io
import math
import re
import shlex
import time
from pathlib import Path

from .evaluate import SUCCESS_RULE_TEXT
from .files import atomic_write, git_revision, one_line
from .intervals import (
    CANNOT_TELL,
    HIGHER,
    LOWER,
    REPLICATES,
    Interval,
    no_difference,
    verdict,
    verdicts,
)
from .jobs import (
    Job,
    Sources,
    announce_training,
    checkpoint_rule,
    only_rows,
    preset_rows,
    run_jobs,
    table_jobs,
    trains,
)
from .metrics import COLUMN_TITLES
from .ray_jobs import run_jobs_on_ray
from .table_spec import (
    CELL_KEYS,
    CELL_TITLES,
    CELLS,
    METRICS,
    SPEC_FILE,
    Comparison,
    Preset,
    TableError,
    TableSpec,
)
from .table_statistics import ComparisonStatistics, PairedDifference, RowResult, TableResult, paper_value
from .zoo import other_code_runs


def run_table(
    spec: TableSpec,
    preset_name: str,
    runs_dir: Path | str = "runs",
    *,
    progress=print,
    workers: int = 1,
    device: str = "cpu",
    sources: Sources | None = None,
    rows_named: tuple[str, ...] = (),
    ray_address: str | None = None,
    ray_node_ip: str | None = None,
) -> TableResult:
    """Every row and seed (a job each, `jobs.run_jobs`), then the table's rows assembled; resumable
    (see the module docstring). `rows_named`: only these rows of the preset (a partial table, its
    caption and file names say so). `workers` > 1 runs that many jobs at once in worker processes
    (torch on the preset's `threads`, else one thread, each); `ray_address`: every job as a task on
    that Ray cluster instead (`ray_node_ip`: this machine's address there). The table is the same
    whichever runs the jobs."""
    preset = spec.preset(preset_name)
    sources = sources or Sources()  # (by default: train, or find, or resume, in runs_dir)
    if workers < 1:
        raise TableError(f"workers must be at least 1, got {workers}")
    runs_dir = Path(runs_dir)
    start = time.perf_counter()
    rows = only_rows(spec, preset, rows_named)
    pairs = [(row, seed) for row, seed in table_jobs(spec, preset) if row in rows]
    if sources.train_only:  # only the jobs that train
        pairs = [(row, seed) for row, seed in pairs if trains(row)]
    if sources.trained is None:
        announce_training(preset, [p for p in pairs if trains(p[0])], runs_dir, device, progress)
    # torch's threads in every job, training (the option) and evaluation alike: the spec's, so that a
    # job's numbers do not depend on how many run at once (threads change the sums' order)
    jobs = [
        Job(
            spec=spec,
            preset=preset,
            row=row,
            seed=seed,
            runs_dir=runs_dir,
            device=device,
            sources=sources,
            threads=preset.threads,
        )  # fmt: skip
        for row, seed in pairs
    ]
    if ray_address is None:
        outcomes = run_jobs(jobs, progress, workers)
    else:
        outcomes = run_jobs_on_ray(jobs, ray_address, progress, ray_node_ip)
    if sources.trained is not None:
        other_code_runs([outcome.train_run for outcome in outcomes if outcome.train_run], progress)
    per_row: dict[str, RowResult] = {}
    for job, outcome in zip(jobs, outcomes, strict=True):
        result = per_row.setdefault(job.row.name, RowResult(job.row, [], [], [], 0.0))
        result.episodes.append(outcome.cells)
        result.train_runs.append(outcome.train_run)
        result.eval_runs.append(outcome.eval_run)
        result.seconds += outcome.seconds
    results = [per_row[row.name] for row in rows if row.name in per_row]  # (training only: trained rows)
    left_out = tuple(row.name for row in preset_rows(spec, preset) if row not in rows)
    return TableResult(spec, preset, results, time.perf_counter() - start, git_revision(), left_out)


NONE = "–"  # no episodes in the cell, or not in the paper
NO_COMPARISON = "No comparison of the spec has both its rows in this table."


def _no_comparison_here(result: TableResult) -> bool:
    """The spec draws comparisons, but none has both its rows in this table (a partial one)."""
    return bool(result.spec.comparisons) and not result.statistics().comparisons


def interval_text(interval: Interval | None, signed: bool = False) -> str:
    """'52.6 [48.1, 57.0]' (a difference: '+4.1 [-0.3, +8.2]'); '–' for none."""
    if interval is None:
        return NONE
    f = "+.1f" if signed else ".1f"
    estimate, low, high = (x + 0.0 for x in (interval.estimate, interval.low, interval.high))  # no -0.0
    return f"{estimate:{f}} [{low:{f}}, {high:{f}}]"


def paper_text(value: float | None, signed: bool = False) -> str:
    """The paper's number as printed (2 decimals); '–' where it has none."""
    return NONE if value is None else f"{value:{'+.2f' if signed else '.2f'}}"


CHECKPOINT_TEXT = {
    "best_val_sr": (
        "the checkpoint with the best validation SR (ties to the later; FF A3C, whose scene-specific "
        "layers exist for its training kitchens only, validated on their seen targets from training "
        "starts that are no fixed episode's, leaving out a target that has none)"
    ),
    "last": "each run's final weights (last.pt), not the paper's rule of the best validation SR",
}


def caption(result: TableResult) -> str:
    p, pr = result.preset, result.spec.protocol
    rule = SUCCESS_RULE_TEXT[pr.success_rule]
    if p.score_rule and p.score_rule != pr.success_rule:  # (table_spec allows only visible here)
        rule = (
            f"{SUCCESS_RULE_TEXT[p.score_rule]} (SAVN's rule; the evaluations run under "
            f"{SUCCESS_RULE_TEXT[pr.success_rule]}, scored under it: Stop ends the episode under both, so "
            "the episodes are the same)"
        )
    stop = "Stop ends the episode" if pr.stop_ends else "a wrong Stop is a no-op"
    if pr.success_rule == "arrival":
        stop = "Stop is a no-op"
    one_seed = " (one seed: the interval covers episodes only)" if p.seeds == 1 and not p.row_seeds else ""
    some = p.unseen_target_kitchens
    unseen = f" (unseen targets in {len(some)} of the training kitchens: {', '.join(some)})" if some else ""
    return (
        f"Table I regenerated by kgnavbench, preset {p.name!r} ({p.description}): {p.frames:,} training "
        f"frames per learned row, {p.episodes} of the 100 fixed episodes per target, {p.seeds_text()}; "
        f"success = {rule}, {stop}; caps {pr.seen_cap} (seen kitchens, seen targets) / {pr.unseen_cap}; "
        f"{CHECKPOINT_TEXT[checkpoint_rule(result.spec, p)]}. Cells: SPL and SR in %, ours as the mean over "
        f"{p.seeds_text()}, 95% stratified bootstrap interval over seeds and episodes ({REPLICATES} "
        f"replicates){one_seed}; the paper's as printed on the line '(paper)'; seen/seen and seen/unseen: "
        f"seen kitchens with seen or unseen targets{unseen}; '–': no episodes in the cell, or none in the "
        f"paper. Git {result.git_revision}, wall time {result.seconds / 60:.1f} min."
        # "; ": a row's name may hold a comma ("+IL+TSE, object detections, no graph")
        + (f" Partial: without the preset's rows {'; '.join(result.left_out)}." if result.left_out else "")
    )


def _header() -> list[str]:
    return ["method"] + [f"{CELL_TITLES[cell]} {metric}" for cell in CELL_KEYS for metric in METRICS]


def table_rows(result: TableResult) -> list[list[str]]:
    """Two lines per row: ours (mean [95% interval]) and the paper's ('–' for a row that is ours)."""
    stats = result.statistics()
    lines = []
    for r in result.rows:
        name = r.row.name
        ours = [interval_text(stats.cells[(name, c, m)].interval) for c in CELL_KEYS for m in METRICS]
        paper = [paper_text(paper_value(r.row, c, m)) for c in CELL_KEYS for m in METRICS]
        lines += [[name, *ours], [f"{name} (paper)", *paper]]
    return lines


def verdict_rules(margin: float) -> str:
    """The verdicts, as every caption of a table of differences states them (`intervals.verdict`)."""
    return (
        f"Each verdict reads one 95% interval (so among many cells a few are wrong by chance), at a margin "
        f"of {margin:g} points, first that applies: where the paper has a side (its difference d at least "
        "0.5 points), holds (the interval excludes 0 on the paper's side and contains d), holds, smaller "
        "than the paper's (d lies beyond it), holds, larger than the paper's (d lies between 0 and it), "
        "reversed (it excludes 0 on the other side); where the paper has no side (no difference printed, or "
        f"one below 0.5 points), higher or lower (it excludes 0); {no_difference(margin)} (it lies within "
        f"±{margin:g}); smaller than the paper's (it contains 0 and excludes d); cannot tell."
    )


def ablation_intro(margin: float) -> str:
    return (
        "For each comparison the paper draws and each cell: other − base in percentage points, the paper's "
        "(as printed) and ours (the difference of the two rows' means, with the 95% interval of the "
        "differences of their independent bootstrap replicates), and the verdict. "
        + verdict_rules(margin)
        + " '–': no episodes."
    )


def _ablation_header() -> list[str]:
    head = ["comparison", "cell"]
    for metric in METRICS:
        head += [f"{metric} paper", f"{metric} ours", f"{metric} verdict"]
    return head


def _ablation_lines(comparisons, statistics: list[ComparisonStatistics]) -> list[list[str]]:
    by_key = {(s.comparison, s.cell, s.metric): s for s in statistics}
    lines = []
    for comparison in comparisons:
        for cell in CELL_KEYS:
            if (comparison, cell, METRICS[0]) not in by_key:
                continue
            line = [f"{comparison.other} − {comparison.base}", CELL_TITLES[cell]]
            for metric in METRICS:
                s = by_key[(comparison, cell, metric)]
                line += [
                    paper_text(s.paper_difference, signed=True),
                    interval_text(s.ours, signed=True),
                    s.verdict or NONE,
                ]
            lines.append(line)
    return lines


def _counts(items, verdicts: tuple[str, ...]) -> str:
    """'SPL: 3 holds; 0 reversed; ... . SR: ...': how many of `items` (each with a metric and a verdict,
    None where it has no episodes) have each of `verdicts`, per metric (a verdict may hold a comma)."""
    parts = []
    for metric in METRICS:
        found = [i.verdict for i in items if i.metric == metric and i.verdict]
        parts.append(f"{metric}: " + "; ".join(f"{found.count(v)} {v}" for v in verdicts))
    return ". ".join(parts)


def _md_cell(text: str) -> str:
    """A markdown table cell: one line, its pipes escaped (a row named 'a | b' stays one cell)."""
    return one_line(text).replace("\\", "\\\\").replace("|", "\\|")


def _markdown_table(head: list[str], rows: list[list[str]], numeric: set[int]) -> list[str]:
    """A markdown table; the columns numbered in `numeric` right-aligned; every cell escaped."""
    align = "|" + "".join("---:|" if i in numeric else "---|" for i in range(len(head)))
    lines = ["| " + " | ".join(map(_md_cell, head)) + " |", align]
    return lines + ["| " + " | ".join(map(_md_cell, row)) + " |" for row in rows]


def to_markdown(result: TableResult) -> str:
    lines = [f"**{caption(result)}**", ""]
    head = _header()
    lines += _markdown_table(head, table_rows(result), numeric=set(range(1, len(head))))
    if _no_comparison_here(result):
        lines += ["", f"**Ablation check.** {NO_COMPARISON}"]
    elif result.spec.comparisons:
        statistics = result.statistics().comparisons
        lines += _ablation_markdown(result.spec.comparisons, statistics, result.spec.protocol.margin)
    return "\n".join(lines) + "\n"


def _ablation_markdown(comparisons, statistics: list[ComparisonStatistics], margin: float) -> list[str]:
    """The markdown ablation check: its intro, a line per comparison and cell, the verdicts counted."""
    lines = ["", f"**Ablation check.** {ablation_intro(margin)}", ""]
    head = _ablation_header()  # comparison, cell, then per metric: paper, ours, verdict
    numbers = {i for i in range(2, len(head)) if (i - 2) % 3 != 2}
    lines += _markdown_table(head, _ablation_lines(comparisons, statistics), numeric=numbers)
    return lines + ["", f"Verdicts: {_counts(statistics, verdicts(margin))}."]


def _number(value: float | None) -> str:
    """A CSV number: 6 significant digits; empty for none (never NaN)."""
    return "" if value is None else f"{value + 0.0:.6g}"  # + 0.0: 0, never -0


def to_csv(result: TableResult) -> str:
    """Tidy: one line per row, cell and metric; each seed's own value in seed_0, seed_1, ..."""
    stats = result.statistics()
    seeds = max((len(r.episodes) for r in result.rows), default=0)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["# " + caption(result)])
    head = ["row", "method", "column", "kind", "metric", "mean", "ci_low", "ci_high", "paper"]
    writer.writerow(head + ["episodes_per_seed"] + [f"seed_{s}" for s in range(seeds)])
    for r in result.rows:
        for cell, (column, kind) in zip(CELL_KEYS, CELLS):
            for metric in METRICS:
                s = stats.cells[(r.row.name, cell, metric)]
                i = s.interval
                counts = sorted(set(s.episodes_per_seed))
                writer.writerow(
                    [r.row.name, r.row.method, column, kind, metric]
                    + [_number(i.estimate if i else None), _number(i.low if i else None)]
                    + [_number(i.high if i else None), _number(paper_value(r.row, cell, metric))]
                    # every seed runs the same episodes: one count (several, ';'-joined, would be a bug)
                    + [";".join(str(n) for n in counts)]
                    + [_number(m) for m in s.seed_means]
                    + [""] * (seeds - len(s.seed_means))
                )
    return out.getvalue()


def to_ablation_csv(result: TableResult) -> str:
    """Tidy: one line per comparison, cell and metric: the paper's two values and difference, ours with
    its 95% interval, the verdict (empty where we have no episodes)."""
    none = "" if result.statistics().comparisons else NO_COMPARISON + " "
    intro = ablation_intro(result.spec.protocol.margin)
    return _ablation_csv(
        "# Ablation check: " + none + intro + " " + caption(result), result.statistics().comparisons
    )


ABLATION_CSV_FIELDS = ["base", "other", "column", "kind", "metric", "paper_base", "paper_other"]
ABLATION_CSV_FIELDS += ["paper_difference", "difference", "ci_low", "ci_high", "verdict"]


def _ablation_csv(header: str, statistics: list[ComparisonStatistics]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow([header])
    writer.writerow(ABLATION_CSV_FIELDS)
    for s in statistics:
        column, _, kind = s.cell.partition("/")
        i = s.ours
        writer.writerow(
            [s.comparison.base, s.comparison.other, column, kind, s.metric]
            + [_number(s.paper_base), _number(s.paper_other), _number(s.paper_difference)]
            + [_number(i.estimate if i else None), _number(i.low if i else None)]
            + [_number(i.high if i else None), s.verdict or ""]
        )
    return out.getvalue()


def reverdict_tables(spec: TableSpec, preset_name: str, out_dir: Path | str) -> Written:
    """The verdicts of a preset's written tables recomputed under the spec's rules and margin, from the
    intervals its ablation CSV holds (6 significant digits), nothing trained or evaluated: the CSV's
    verdicts and header, and the ablation check of its .md and .tex where they exist (their main table
    is kept as written). For tables whose runs or evaluations are not at hand (the quick tables, whose
    evaluations are not kept), after a change of the verdict rules.

    The CSV is checked whole before anything is written, since a verdict read from a damaged line, or
    tables whose comparisons are no longer the spec's, would look as good as the real ones: a bad
    number (nan, inf, text), an interval upside down or given in part, a line cut, deleted or repeated, a
    comparison of the spec the CSV lacks or one it has that the spec no longer draws, each is one
    TableError naming the file and the line or comparison, and the tables stay as they were."""
    preset = spec.preset(preset_name)
    stem = Path(out_dir) / table_stem(preset.name)
    path = stem.parent / f"{stem.name}-ablation.csv"
    lines = _read_table_file(path).splitlines()
    if not lines:
        raise TableError(f"{path}: empty, not an ablation CSV kgnavbench wrote")
    old_intro_end = "'–': no episodes. "  # the intro's last words, then the table's caption
    if not lines[0].startswith('"# Ablation check: ') or old_intro_end not in lines[0]:
        raise TableError(
            f"{path}, line 1: not an ablation CSV kgnavbench wrote (its first line is no caption)"
        )
    header = next(csv.reader([lines[0]]))[0]
    table_caption = header[header.index(old_intro_end) + len(old_intro_end) :]
    none = NO_COMPARISON + " " if header.startswith("# Ablation check: " + NO_COMPARISON) else ""
    records = _ablation_records(path, lines[1:])
    if not records and not none:
        raise TableError(f"{path}: no comparison lines")
    if records and none:
        first = min(n for n, _ in records.values())
        raise TableError(f"{path}, line {first}: a comparison line, where the caption says there is none")
    rows, rows_source = _table_row_names(spec, preset, stem.parent / f"{stem.name}.csv")
    comparisons = _check_comparisons(
        path, spec, rows, rows_source, records, _regenerate(spec, preset, out_dir)
    )
    margin = spec.protocol.margin
    statistics = []
    # in the spec's order, as the writer has them (`table_statistics`)
    for comparison in comparisons:
        for cell in CELL_KEYS:
            for metric in METRICS:
                _, number = records[(comparison, cell, metric)]
                ours = None
                if number["difference"] is not None:
                    ours = Interval(number["difference"], number["ci_low"], number["ci_high"])
                paper = number["paper_difference"]
                judged = verdict(paper, ours.low, ours.high, margin) if ours else None
                statistics.append(
                    ComparisonStatistics(
                        comparison, cell, metric, number["paper_base"], number["paper_other"], paper, ours,
                        judged,
                    )
                )  # fmt: skip
    intro = ablation_intro(margin)
    files = [
        (path.name, _ablation_csv("# Ablation check: " + none + intro + " " + table_caption, statistics))
    ]
    md, tex = stem.parent / f"{stem.name}.md", stem.parent / f"{stem.name}.tex"
    if none:  # no comparison in the table: its .md and .tex say so, with nothing to recompute
        return _write_files(stem.parent, tuple(files))
    md_text = _read_table_file(md) if md.exists() else ""
    if "\n\n**Ablation check.** " in md_text:
        kept = md_text[: md_text.index("\n\n**Ablation check.** ")]
        files.append(
            (md.name, "\n".join([kept, *_ablation_markdown(comparisons, statistics, margin)]) + "\n")
        )
    tex_text = _read_table_file(tex) if tex.exists() else ""
    if TEX_ABLATION in tex_text:
        kept = tex_text[: tex_text.index(TEX_ABLATION)]
        files.append((tex.name, kept + "\n".join(_ablation_latex(comparisons, statistics, margin)) + "\n"))
    return _write_files(stem.parent, tuple(files))


def _read_table_file(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise TableError(f"cannot read {path}: {getattr(e, 'strerror', None) or e}") from e


# an ablation CSV's line: (comparison, cell, metric) -> (its line number, its numbers by field)
AblationRecords = dict[tuple[Comparison, str, str], tuple[int, dict[str, float | None]]]


def _ablation_records(path: Path, lines: list[str]) -> AblationRecords:
    """The lines of an ablation CSV after its caption, the header first, each line checked on its own;
    a TableError names the first bad line and what is wrong with it."""
    reader = csv.reader(lines)
    records: AblationRecords = {}
    try:
        head = next(reader, None)
        if head != ABLATION_CSV_FIELDS:
            missing = [name for name in ABLATION_CSV_FIELDS if name not in (head or [])]
            what = f"no column {', '.join(missing)}" if missing else "its columns in another order"
            if len(missing) == len(ABLATION_CSV_FIELDS):
                what = "none of its columns: no header"
            raise TableError(
                f"{path}, line 2: not the header of an ablation CSV ({what}; the header is "
                f"{','.join(ABLATION_CSV_FIELDS)})"
            )
        for values in reader:
            n = reader.line_num + 1  # + 1: the caption, not given to the reader
            if not values:
                continue  # a blank line: what it lost, if anything, the lines missing tell
            if len(values) != len(ABLATION_CSV_FIELDS):
                raise TableError(
                    f"{path}, line {n}: {len(values)} values where the header has "
                    f"{len(ABLATION_CSV_FIELDS)} (a cut or damaged line)"
                )
            key, numbers = _ablation_line(path, n, dict(zip(ABLATION_CSV_FIELDS, values)))
            if key in records:
                raise TableError(
                    f"{path}, line {n}: {_comparison_name(key[0])}, cell {key[1]}, {key[2]} again "
                    f"(line {records[key][0]} has it)"
                )
            records[key] = (n, numbers)
    except csv.Error as e:
        raise TableError(f"{path}, line {reader.line_num + 1}: not a line of an ablation CSV ({e})") from e
    return records


def _ablation_line(
    path: Path, n: int, record: dict[str, str]
) -> tuple[tuple[Comparison, str, str], dict[str, float | None]]:
    """Line `n` of an ablation CSV: its key and numbers, or a TableError saying what is wrong."""
    cell = f"{record['column']}/{record['kind']}"
    if cell not in CELL_KEYS:
        raise TableError(
            f"{path}, line {n}: no cell of Table I is column {record['column']!r}, kind {record['kind']!r}"
        )
    if record["metric"] not in METRICS:
        raise TableError(f"{path}, line {n}: metric {record['metric']!r} is none of {', '.join(METRICS)}")
    numbers = {name: _csv_number(path, n, name, record[name]) for name in ABLATION_CSV_FIELDS[5:11]}
    interval = [numbers[name] for name in ("difference", "ci_low", "ci_high")]
    if None in interval and interval != [None] * 3:  # all three, or none for a cell without episodes
        raise TableError(
            f"{path}, line {n}: difference, ci_low and ci_high must be all given or all empty (no episodes), "
            f"not {record['difference']!r}, {record['ci_low']!r}, {record['ci_high']!r}"
        )
    if interval[1] is not None and interval[1] > interval[2]:
        raise TableError(
            f"{path}, line {n}: the interval's low end (ci_low {record['ci_low']}) is above its high end "
            f"(ci_high {record['ci_high']})"
        )
    return (Comparison(record["base"], record["other"]), cell, record["metric"]), numbers


def _csv_number(path: Path, n: int, name: str, text: str) -> float | None:
    """A number of an ablation CSV's line, None where empty. float() takes 'nan' and 'inf', from which
    a verdict would be read all the same (nan compares false with everything): refused."""
    if not text:
        return None
    try:
        value = float(text)
    except ValueError:
        raise TableError(f"{path}, line {n}: {name} is {text!r}, not a number") from None
    if not math.isfinite(value):
        raise TableError(f"{path}, line {n}: {name} is {text!r}, not a finite number")
    return value


def _comparison_name(comparison: Comparison) -> str:
    return f"comparison {comparison.other!r} against {comparison.base!r}"


def _table_row_names(spec: TableSpec, preset: Preset, main_csv: Path) -> tuple[set[str], str]:
    """The rows of the written table, and where they come from: those its main CSV names (the rows it
    was written with, which decide the comparisons it draws), the preset's where there is none."""
    if not main_csv.exists():
        return {row.name for row in preset_rows(spec, preset)}, f"the spec's preset {preset.name!r}"
    reader = csv.reader(_read_table_file(main_csv).splitlines()[1:])  # [1:]: its caption
    try:
        head = next(reader, None) or []
        if "row" not in head:
            raise TableError(f"{main_csv}, line 2: no column row, so the table's rows are unknown")
        i = head.index("row")
        return {values[i] for values in reader if len(values) > i}, str(main_csv)
    except csv.Error as e:
        raise TableError(f"{main_csv}, line {reader.line_num + 1}: not a line of a table CSV ({e})") from e


def _regenerate(spec: TableSpec, preset: Preset, out_dir: Path | str) -> str:
    """The command that writes the preset's tables again from its runs, with the spec and folder given."""
    command = f"kgnavbench table --preset {shlex.quote(preset.name)}"
    if spec.path.resolve() != SPEC_FILE.resolve():
        command += f" --spec {shlex.quote(str(spec.path))}"
    if Path(out_dir).resolve() != spec.path.parent.resolve():
        command += f" --out {shlex.quote(str(out_dir))}"
    return command


def _check_comparisons(
    path: Path, spec: TableSpec, rows: set[str], rows_source: str, records: AblationRecords, regenerate: str
) -> list[Comparison]:
    """The comparisons of the spec whose rows are both in the table, in the spec's order: those the
    writer draws. The CSV must have every line of each and no other: a comparison it lacks has no
    interval to recompute, and lines of one the spec no longer draws are neither the spec's tables
    nor to be dropped unsaid; either is a TableError."""
    expected = [c for c in spec.comparisons if c.base in rows and c.other in rows]
    first_line: dict[Comparison, int] = {}
    for (comparison, _, _), (n, _) in records.items():
        first_line.setdefault(comparison, n)
    for comparison, n in first_line.items():
        if comparison not in spec.comparisons:
            raise TableError(
                f"{path}, line {n}: {_comparison_name(comparison)} is not in the spec {spec.path} any more; "
                f"its lines are neither kept nor dropped: regenerate the tables ({regenerate}), or put the "
                "comparison back in the spec"
            )
        if comparison not in expected:
            absent = [name for name in (comparison.base, comparison.other) if name not in rows]
            raise TableError(
                f"{path}, line {n}: {_comparison_name(comparison)}, but the table has no row "
                f"{', '.join(map(repr, absent))} (its rows: those of {rows_source}); regenerate the tables "
                f"({regenerate})"
            )
    for comparison in expected:
        if comparison not in first_line:
            raise TableError(
                f"{path}: no line of the spec's {_comparison_name(comparison)} (both its rows are in the "
                f"table); its intervals cannot be recomputed from this CSV: regenerate the tables "
                f"({regenerate})"
            )
        for cell in CELL_KEYS:
            for metric in METRICS:
                if (comparison, cell, metric) not in records:
                    raise TableError(
                        f"{path}: no line for {_comparison_name(comparison)}, cell {cell}, {metric} (deleted "
                        f"or cut?); restore the file or regenerate the tables ({regenerate})"
                    )
    return expected


TEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "_": r"\_",
    "#": r"\#",
    "$": r"\$",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def _tex_escape(text: str) -> str:
    """A LaTeX table cell: LaTeX's special characters escaped in one pass, on one line."""
    text = "".join(TEX_SPECIAL.get(ch, ch) for ch in one_line(text))
    if not any(ch.isalpha() for ch in text):
        text = text.replace("-", "$-$")  # a number's minus sign, not a hyphen
    return text.replace("−", "$-$").replace("–", "--")


def _tex_tabular(spec: str, head: list[str], rows: list[list[str]]) -> list[str]:
    lines = [r"\resizebox{\textwidth}{!}{%", r"\begin{tabular}{" + spec + "}", r"\hline"]
    lines += head + [r"\hline"]
    lines += [" & ".join(_tex_escape(c) for c in row) + r" \\" for row in rows]
    return lines + [r"\hline", r"\end{tabular}}"]


def to_latex(result: TableResult) -> str:
    """Table I with intervals and the paper's numbers, then the ablation check (needs graphicx)."""
    kinds = [("static", 3), ("actionable", 2)]  # CELLS: three static cells, then two actionable
    groups = " & ".join(rf"\multicolumn{{{2 * n}}}{{c}}{{{kind} targets}}" for kind, n in kinds)
    columns = " & ".join(rf"\multicolumn{{2}}{{c}}{{{COLUMN_TITLES[column]}}}" for column, _ in CELLS)
    head = [rf" & {groups} \\", rf" & {columns} \\", " & " + " & ".join(["SPL & SR"] * len(CELLS)) + r" \\"]
    lines = [
        "% needs \\usepackage{graphicx} (\\resizebox)",
        r"\begin{table*}",
        r"\centering",
        r"\caption{" + _tex_escape(caption(result)) + "}",
    ]
    lines += _tex_tabular("l" + "rr" * len(CELLS), head, table_rows(result))
    lines.append(r"\end{table*}")
    if _no_comparison_here(result):
        lines.append("% Ablation check. " + NO_COMPARISON)
    elif result.spec.comparisons:
        statistics = result.statistics().comparisons
        lines += _ablation_latex(result.spec.comparisons, statistics, result.spec.protocol.margin)
    return "\n".join(lines) + "\n"


TEX_ABLATION = r"\begin{table*}" + "\n" + r"\centering" + "\n" + r"\caption{Ablation check. "


def _ablation_latex(comparisons, statistics: list[ComparisonStatistics], margin: float) -> list[str]:
    """The LaTeX ablation check: a table* whose caption is its intro (TEX_ABLATION starts it)."""
    metrics = " & ".join(rf"\multicolumn{{3}}{{c}}{{{metric}}}" for metric in METRICS)
    head = [
        rf" & & {metrics} \\",
        "comparison & cell & " + " & ".join(["paper & ours & verdict"] * len(METRICS)) + r" \\",
    ]
    lines = [TEX_ABLATION + _tex_escape(ablation_intro(margin)) + "}"]
    lines += _tex_tabular("ll" + "rrl" * len(METRICS), head, _ablation_lines(comparisons, statistics))
    return lines + [r"\end{table*}"]


def table_stem(preset_name: str) -> str:
    """The files' stem of a preset's table: table1 for the quick preset (`make table`), table1-<preset>."""
    return "table1" if preset_name == "quick" else f"table1-{preset_name}"


def write_table(result: TableResult, out_dir: Path | str) -> Written:
    """tables/table1.{md,csv,tex} and table1-ablation.csv for the quick preset, table1-<preset>.* and
    table1-<preset>-ablation.csv for the others; `-partial` after the preset's name for a table without
    some of its rows (`--row`), so that it never overwrites the whole one (a later partial table of the
    same preset replaces an earlier one)."""
    stem = table_stem(result.preset.name) + ("-partial" if result.left_out else "")
    return _write_files(
        out_dir,
        (
            (f"{stem}.md", to_markdown(result)),
            (f"{stem}.csv", to_csv(result)),
            (f"{stem}-ablation.csv", to_ablation_csv(result)),
            (f"{stem}.tex", to_latex(result)),
        ),
    )


class Written(list):
    """The paths of a table's files (a list), and `kept`: those left as they were, since their new
    text differs from the old only in the caption's provenance (git revision, wall time): rewriting a
    committed table from the same archive leaves the tree clean."""

    def __init__(self, paths=(), kept=()):
        super().__init__(paths)
        self.kept = list(kept)

    def __iadd__(self, other):
        self.extend(other)
        self.kept += getattr(other, "kept", [])
        return self

    def summary(self) -> str:
        """'wrote A, B' with the files kept named apart."""
        wrote = [str(p) for p in self if p not in self.kept]
        parts = [f"wrote {', '.join(wrote)}"] if wrote else []
        if self.kept:
            parts.append(
                f"kept {', '.join(map(str, self.kept))} (the same table; only the caption's git revision "
                "and wall time would change)"
            )
        return "; ".join(parts)


PROVENANCE = re.compile(r"Git [0-9A-Za-z-]+|wall time [0-9.]+ min")


def _write_files(out_dir: Path | str, files: tuple[tuple[str, str], ...]) -> Written:
    """Each (name, text) atomically into OUT_DIR/name, unless the file there says the same but for
    its provenance; a failure is one TableError naming the file."""
    written = Written()
    for name, text in files:
        path = Path(out_dir) / name
        try:
            old = path.read_text() if path.is_file() else None
        except (OSError, UnicodeDecodeError):
            old = None
        if old is not None and old != text and PROVENANCE.sub("", old) == PROVENANCE.sub("", text):
            written.kept.append(path)
        else:
            try:
                atomic_write(path, text)
            except OSError as e:
                raise TableError(f"cannot write {path}: {e.strerror or e}") from e
        written.append(path)
    return written


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
    return _counts(diffs, (HIGHER, LOWER, no_difference(margin), CANNOT_TELL))


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
        lines += ["", *_markdown_table(head, body, numeric=set(range(1, len(head))))]
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
            [d.row, column, kind, d.metric, _number(i.estimate if i else None)]
            + [_number(i.low if i else None), _number(i.high if i else None), d.verdict or ""]
        )
    return out.getvalue()


def write_paired(
    result: TableResult, base: TableResult, diffs: list[PairedDifference], out_dir: Path | str
) -> Written:
    """table1-<preset>-against-<base>.md and .csv (`-partial` after the preset's name as `write_table`)."""
    stem = f"table1-{result.preset.name}{'-partial' if result.left_out else ''}-against-{base.preset.name}"
    return _write_files(
        out_dir,
        (
            (f"{stem}.md", to_paired_markdown(result, base, diffs)),
            (f"{stem}.csv", to_paired_csv(result, base, diffs)),
        ),
    )
