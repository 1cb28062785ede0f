"""Stage 33 — reverdict: a preset's written tables given the spec's current verdicts
(`table --verdicts-only`), from the intervals their ablation CSV holds, nothing trained or evaluated.

For tables whose runs or evaluations are not at hand (the quick tables, whose evaluations are not
kept), after a change of the verdict rules. The CSV is checked whole before anything is written: a
damaged line or a comparison the spec no longer draws is one TableError, and the tables stay as they
were.
"""

from __future__ import annotations

import csv
import math
import shlex
from pathlib import Path

from .intervals import (
    Interval,
    verdict,
)
from .jobs import (
    preset_rows,
)
from .table_files import (
    ABLATION_CSV_FIELDS,
    NO_COMPARISON,
    TEX_ABLATION,
    Written,
    ablation_csv,
    ablation_intro,
    ablation_latex,
    ablation_markdown,
    table_stem,
    write_files,
)
from .table_spec import (
    CELL_KEYS,
    METRICS,
    SPEC_FILE,
    Comparison,
    Preset,
    TableError,
    TableSpec,
)
from .table_statistics import ComparisonStatistics


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
    files = [(path.name, ablation_csv("# Ablation check: " + none + intro + " " + table_caption, statistics))]
    md, tex = stem.parent / f"{stem.name}.md", stem.parent / f"{stem.name}.tex"
    if none:  # no comparison in the table: its .md and .tex say so, with nothing to recompute
        return write_files(stem.parent, tuple(files))
    md_text = _read_table_file(md) if md.exists() else ""
    if "\n\n**Ablation check.** " in md_text:
        kept = md_text[: md_text.index("\n\n**Ablation check.** ")]
        files.append((md.name, "\n".join([kept, *ablation_markdown(comparisons, statistics, margin)]) + "\n"))
    tex_text = _read_table_file(tex) if tex.exists() else ""
    if TEX_ABLATION in tex_text:
        kept = tex_text[: tex_text.index(TEX_ABLATION)]
        files.append((tex.name, kept + "\n".join(ablation_latex(comparisons, statistics, margin)) + "\n"))
    return write_files(stem.parent, tuple(files))


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
