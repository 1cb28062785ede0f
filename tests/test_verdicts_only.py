"""`kgnavbench table --verdicts-only` refuses an ablation CSV it cannot trust: a damaged number, interval
or line, a missing header or column, an empty file, a comparison the spec added or removed since the
tables were written. Each is one line on stderr and exit status 2, and the tables stay byte for byte
as they were (everything is checked before anything is written)."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pytest
from test_table import episode  # (pytest puts tests/ on the path)

from kgnavbench.cli import main
from kgnavbench.table_files import ABLATION_CSV_FIELDS, write_table
from kgnavbench.table_spec import SPEC_FILE, Preset, load_spec
from kgnavbench.table_statistics import RowResult, TableResult, cell_episodes

ABLATION = "table1-ablation.csv"  # the quick preset's
# the committed spec draws both comparisons of these rows: +KG against +IL+TSE, +KG+Attention against +KG
ROWS = ("+IL+TSE", "+KG", "+KG+Attention")
KG_BLOCK = '[[comparisons]]\nbase = "+KG"\nother = "+KG+Attention"\n'


def written_tables(folder: Path) -> Path:
    """The quick preset's tables of three rows, two seeds each, under the committed spec: each row has
    episodes in two cells (so its comparisons have intervals there) and none in the other three."""
    spec = load_spec()
    rows = {r.name: r for r in spec.rows}

    def row(name: str, wins: int) -> RowResult:
        seeds = [
            [
                episode("seen_seen", "static", t, i < wins + seed, path=10 + 5 * seed)
                for i, t in enumerate("AABB")
            ]
            + [
                episode("unseen_kitchens", "static", t, i < wins, path=20, kitchen="FloorPlan30")
                for i, t in enumerate("CCD")
            ]
            for seed in range(2)
        ]
        return RowResult(rows[name], [cell_episodes(s) for s in seeds], ["r"] * 2, ["e"] * 2, 1)

    result = TableResult(
        spec=spec,
        preset=Preset("quick", "a test", 1000, 2, 2, (), (), {}),
        rows=[row(name, wins) for name, wins in zip(ROWS, (0, 1, 3))],
        seconds=90.0,
        git_revision="abc123",
    )
    folder.mkdir()
    write_table(result, folder)
    return folder


def read_ablation(folder: Path) -> tuple[str, list[list[str]]]:
    """The ablation CSV's caption line as written, and its other lines (the header first) as values."""
    caption, *rest = (folder / ABLATION).read_text().splitlines()
    return caption, list(csv.reader(rest))


def write_ablation(folder: Path, caption: str, lines: list[list[str]]) -> None:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows(lines)  # as the writer quotes: the rest stays the same
    (folder / ABLATION).write_text(caption + "\n" + out.getvalue())


def with_interval(lines: list[list[str]]) -> int:
    """The index in `lines` of the first comparison line with an interval (our difference given)."""
    return next(i for i, values in enumerate(lines) if i and values[ABLATION_CSV_FIELDS.index("difference")])


def set_value(name: str, value: str):
    """A damage: the first line with an interval gets `value` in its field `name`."""

    def damage(folder: Path, tmp_path: Path) -> list[str]:
        caption, lines = read_ablation(folder)
        lines[with_interval(lines)][ABLATION_CSV_FIELDS.index(name)] = value
        write_ablation(folder, caption, lines)
        return []

    return damage


def upside_down(folder: Path, tmp_path: Path) -> list[str]:
    caption, lines = read_ablation(folder)
    values = lines[with_interval(lines)]
    low, high = ABLATION_CSV_FIELDS.index("ci_low"), ABLATION_CSV_FIELDS.index("ci_high")
    values[low] = f"{float(values[high]) + 10:g}"
    write_ablation(folder, caption, lines)
    return []


def delete_line(folder: Path, tmp_path: Path) -> list[str]:
    caption, lines = read_ablation(folder)
    del lines[with_interval(lines)]
    write_ablation(folder, caption, lines)
    return []


def cut_line(folder: Path, tmp_path: Path) -> list[str]:
    """The file cut off in the middle of a line: that line short of values, the lines after it gone."""
    caption, lines = read_ablation(folder)
    i = with_interval(lines)
    write_ablation(folder, caption, lines[:i] + [lines[i][:7]])
    return []


def repeat_line(folder: Path, tmp_path: Path) -> list[str]:
    caption, lines = read_ablation(folder)
    i = with_interval(lines)
    lines.insert(i + 1, lines[i])
    write_ablation(folder, caption, lines)
    return []


def drop_column(folder: Path, tmp_path: Path) -> list[str]:
    caption, lines = read_ablation(folder)
    i = ABLATION_CSV_FIELDS.index("ci_high")
    write_ablation(folder, caption, [values[:i] + values[i + 1 :] for values in lines])
    return []


def drop_header(folder: Path, tmp_path: Path) -> list[str]:
    caption, lines = read_ablation(folder)
    write_ablation(folder, caption, lines[1:])
    return []


def empty_file(folder: Path, tmp_path: Path) -> list[str]:
    (folder / ABLATION).write_text("")
    return []


def spec_with(text: str, tmp_path: Path) -> list[str]:
    spec = tmp_path / "spec.toml"
    spec.write_text(text)
    return ["--spec", str(spec)]


def comparison_added(folder: Path, tmp_path: Path) -> list[str]:
    added = '\n[[comparisons]]\nbase = "+IL+TSE"\nother = "+KG+Attention"\n'
    return spec_with(SPEC_FILE.read_text() + added, tmp_path)


def comparison_removed(folder: Path, tmp_path: Path) -> list[str]:
    text = SPEC_FILE.read_text()
    assert KG_BLOCK in text  # (the committed spec draws it)
    return spec_with(text.replace(KG_BLOCK, ""), tmp_path)


def row_not_in_table(folder: Path, tmp_path: Path) -> list[str]:
    """The main CSV without the +IL+TSE row, whose comparison the ablation CSV still has."""
    main_csv = folder / "table1.csv"
    kept = [line for line in main_csv.read_text().splitlines() if not line.startswith("+IL+TSE,")]
    main_csv.write_text("\n".join(kept) + "\n")
    return []


LINE = f"{ABLATION}, line "
KG = "comparison '+KG' against '+IL+TSE'"  # the first comparison of the CSV (the spec's order)
REGENERATE = "regenerate the tables (kgnavbench table --preset quick"

CASES = {
    "nan end": (set_value("ci_high", "nan"), [LINE, "ci_high is 'nan', not a finite number"]),
    "inf end": (set_value("ci_low", "-inf"), [LINE, "ci_low is '-inf', not a finite number"]),
    "inf difference": (set_value("difference", "inf"), [LINE, "difference is 'inf', not a finite number"]),
    "nan paper": (set_value("paper_difference", "NaN"), [LINE, "paper_difference is 'NaN', not a finite"]),
    "not a number": (set_value("ci_low", "abc"), [LINE, "ci_low is 'abc', not a number"]),
    "half an interval": (
        set_value("ci_low", ""),
        [LINE, "difference, ci_low and ci_high must be all given or"],
    ),
    "unknown metric": (set_value("metric", "SPX"), [LINE, "metric 'SPX' is none of SPL, SR"]),
    "unknown cell": (set_value("kind", "moving"), [LINE, "no cell of Table I is column 'seen_seen', kind"]),
    "low above high": (upside_down, [LINE, "the interval's low end (ci_low ", ") is above its high end"]),
    "deleted line": (delete_line, [f"{ABLATION}: no line for {KG}, cell seen_seen/static, SPL"]),
    "cut line": (cut_line, [LINE, "7 values where the header has 12 (a cut or damaged line)"]),
    "repeated line": (repeat_line, [LINE, f"{KG}, cell seen_seen/static, SPL again (line "]),
    "missing column": (drop_column, [f"{LINE}2: not the header of an ablation CSV (no column ci_high;"]),
    "missing header": (
        drop_header,
        [f"{LINE}2: not the header of an ablation CSV (none of its columns: no header;"],
    ),
    "empty file": (empty_file, [f"{ABLATION}: empty, not an ablation CSV kgnavbench wrote"]),
    "comparison added": (
        comparison_added,
        [
            f"{ABLATION}: no line of the spec's comparison '+KG+Attention' against '+IL+TSE'",
            "its intervals cannot be recomputed from this CSV",
            REGENERATE + " --spec ",
        ],
    ),
    "comparison removed": (
        comparison_removed,
        [LINE, "comparison '+KG+Attention' against '+KG' is not in the spec ", REGENERATE + " --spec "],
    ),
    "row not in table": (
        row_not_in_table,
        [
            LINE,
            f"{KG}, but the table has no row '+IL+TSE' (its rows: those of ",
            "table1.csv); " + REGENERATE,
        ],
    ),
}


def test_an_undamaged_csv_re_verdicts_to_the_same_tables(tmp_path, capsys):
    """The fixture's tables are sound: re-verdicted under the margin they were written with, the same."""
    folder = written_tables(tmp_path / "written")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    assert main(["table", "--verdicts-only", "--preset", "quick", "--out", str(folder)]) == 0
    assert "wrote " in capsys.readouterr().out
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before


@pytest.mark.parametrize("case", CASES)
def test_a_csv_it_cannot_trust_is_one_line_and_exit_2_with_nothing_written(case, tmp_path, capsys):
    folder = written_tables(tmp_path / "written")
    damage, says = CASES[case]
    options = damage(folder, tmp_path)
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    capsys.readouterr()
    assert main(["table", "--verdicts-only", "--preset", "quick", "--out", str(folder), *options]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith("kgnavbench: error: ") and err.count("\n") == 1, err
    for words in says:
        assert words in err, err
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
