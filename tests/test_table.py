"""The table stage: the spec and its errors, the writers' text, and (smoke preset) the whole way from
training to the written table, resumed after a kill."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time

import pytest

from kgnavbench import train
from kgnavbench.cli import main
from kgnavbench.table import (
    CELLS,
    SPEC_FILE,
    Preset,
    Row,
    RowResult,
    TableError,
    TableResult,
    combine,
    load_spec,
    parse_spec,
    time_left,
    to_csv,
    to_latex,
    to_markdown,
)


def test_the_committed_spec_has_the_nine_rows_and_three_presets():
    spec = load_spec()
    assert [r.name for r in spec.rows] == [
        "Random walk",
        "IL",
        "FF A3C",
        "LSTM A3C",
        "+IL",
        "+TSE",
        "+IL+TSE",
        "+KG",
        "+KG+Attention",
    ]
    assert {"smoke", "quick", "paper"} <= set(spec.presets)
    assert spec.presets["paper"].frames == 40_000_000 and spec.presets["paper"].episodes == 100
    assert spec.protocol.success_rule == "destination" and spec.protocol.stop_ends
    assert not [r for r in spec.rows if r.name == "FF A3C"][0].unseen_kitchens


GOOD = SPEC_FILE.read_text()


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (
            lambda t: t.replace('success_rule = "destination"', 'success_rule = "nearby"'),
            "protocol.success_rule",
        ),
        (lambda t: t.replace("seen_cap = 100", "seen_cap = 50"), "seen_cap/unseen_cap"),
        (lambda t: t.replace("stop_ends = true", 'stop_ends = "yes"'), "protocol.stop_ends"),
        (lambda t: t.replace('checkpoint = "best_val_sr"', 'checkpoint = "last"'), "protocol.checkpoint"),
        (lambda t: t.replace("frames = 2_000_000", "frames = -5"), "presets.quick.frames"),
        (lambda t: t.replace("frames = 2_000_000", 'frames = "lots"'), "presets.quick.frames"),
        (lambda t: t.replace("episodes = 2\n", "episodes = 101\n"), "presets.quick.episodes"),
        (lambda t: t.replace('train_kitchens = ["FloorPlan1"]', 'train_kitchens = ["Kitchen9"]'), "Kitchen9"),
        (lambda t: t.replace('method = "ff_a3c"', 'method = "ff_a4c"'), "rows[2].method"),
        (lambda t: t.replace('name = "IL"', 'name = "Random walk"'), "row name is used twice"),
        (lambda t: t.replace("[protocol]", "[protocol]\ncolour = 3"), "unknown field(s) colour"),
        (
            lambda t: t.replace("options = {}\npaper_note", "options = { x = [1] }\npaper_note"),
            "rows[0].options.x",
        ),
        (
            lambda t: t + "\n[[rows]]\nname = 'x'\nmethod = 'oracle'\npaper = { 'seen_seen/static' = 3 }\n",
            "paper",
        ),
        (lambda t: t.replace("[protocol]", "[protocol"), "not valid TOML"),
    ],
)
def test_a_bad_spec_gets_one_clear_line_naming_the_field(change, named):
    bad = change(GOOD)
    assert bad != GOOD
    with pytest.raises(TableError, match=None) as e:
        parse_spec(bad, "tables/bad.toml")
    message = str(e.value)
    assert "\n" not in message and "tables/bad.toml" in message and named in message, message


def test_a_missing_spec_file():
    with pytest.raises(TableError, match="nope.toml"):
        load_spec("nope.toml")


def test_cells_combine_over_seeds():
    assert combine([(10.0, 20.0)]) == ("10.00", "20.00")
    assert combine([(10.0, 20.0), (20.0, 40.0)]) == ("15.00 ± 7.07", "30.00 ± 14.14")
    assert combine([None]) == ("–", "–")
    assert combine([None, (1.0, 2.0)]) == ("1.00", "2.00")


def fake_result(seeds: int = 1) -> TableResult:
    spec = load_spec()
    preset = Preset("quick", "a test", 1000, 2, seeds, (), (), {})
    cells = {f"{c}/{k}": (12.5, 25.0) for c, k in CELLS}
    cells["seen_unseen/actionable"] = None
    rows = [
        RowResult(Row("LSTM A3C", "lstm_a3c", {}), [cells] * seeds, ["r"], ["e"], 1.0),
        RowResult(
            Row("Random walk", "random_walk", {}, paper={"seen_seen/static": (0.5, 1.5)}, paper_note="1 / 2"),
            [dict.fromkeys(cells)] * seeds,
            [""],
            ["e"],
            1.0,
        ),
    ]
    return TableResult(spec, preset, rows, 90.0, "abc123")


def test_time_left_per_kind_of_row():
    # before any trained row is done, a random walk's seconds say nothing about the rows to come
    assert time_left([], [False, True, True]) is None
    assert time_left([(False, 2.0)], [True, True]) is None
    # then the mean of each kind times the rows of that kind to come
    assert time_left([(False, 2.0), (True, 60.0), (True, 120.0)], [True, False]) == 90.0 + 2.0
    assert time_left([(True, 60.0)], []) == 0.0


def test_the_writers_text():
    result = fake_result()
    md = to_markdown(result)
    assert "preset 'quick'" in md and "1,000 training frames" in md and "2 of the 100 fixed episodes" in md
    assert "Git abc123" in md and "1.5 min" in md and "Random walk: the paper prints 1 / 2" in md
    lines = [line for line in md.splitlines() if line.startswith("| ")]
    assert lines[0].startswith("| method | seen/seen static SPL | seen/seen static SR |")
    lstm = [line for line in lines if line.startswith("| LSTM A3C |")][0]
    assert lstm.count("12.50") == 5 and lstm.count("25.00") == 5 and lstm.count("–") == 2
    paper = [line for line in lines if line.startswith("| Random walk (paper) |")][0]
    assert "| 0.50 | 1.50 |" in paper
    csv_text = to_csv(result).splitlines()
    assert csv_text[1].startswith("method,seen/seen static SPL") and len(csv_text) == 5
    tex = to_latex(result)
    assert tex.startswith(r"\begin{table*}") and r"\end{tabular}" in tex
    assert r"LSTM A3C & 12.50 & 25.00" in tex and "--" in tex
    assert all(
        line.count("&") == 2 * len(CELLS)
        for line in tex.splitlines()
        if line.endswith(r"\\") and "multicolumn" not in line
    )


def test_several_seeds_show_mean_and_std():
    md = to_markdown(fake_result(seeds=2))
    assert "2 seed(s) (mean ± std)" in md and "12.50 ± 0.00" in md


# ----------------------------------------------------------------------------------------------------
# the smoke preset end to end: train, select, evaluate, write; killed and resumed


def _table_cmd(runs, out) -> list[str]:
    return [
        sys.executable,
        "-m",
        "kgnavbench",
        "table",
        "--preset",
        "smoke",
        "--runs",
        str(runs),
        "--out",
        str(out),
    ]


def _numbers(markdown: str) -> list[str]:
    """The table's lines without the caption (which holds the wall time)."""
    return [line for line in markdown.splitlines() if line.startswith("| ")]


def test_smoke_table_end_to_end_and_resumed_after_a_kill(tmp_path, hermetic_cache):
    env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache)}
    whole = subprocess.run(
        _table_cmd(tmp_path / "a", tmp_path / "a"), capture_output=True, text=True, env=env
    )
    assert whole.returncode == 0, whole.stderr[-2000:]
    table_a = (tmp_path / "a" / "table1-smoke.md").read_text()
    for suffix in (".csv", ".tex"):
        assert (tmp_path / "a" / f"table1-smoke{suffix}").stat().st_size > 500
    rows = _numbers(table_a)
    assert len(rows) == 1 + 9 and all(f"| {name} |" in table_a for name in ("IL", "+KG+Attention"))
    assert "preset 'smoke'" in table_a and "Git " in table_a

    # the checkpoint rule: best.pt is the validation with the best SR, the latest on a tie
    for run in (tmp_path / "a" / "train").iterdir():
        lines = list(csv.DictReader((run / "metrics.csv").read_text().splitlines()))
        validations = [(float(r["val_sr"]), int(r["frames"])) for r in lines if r["val_sr"]]
        best = max(sr for sr, _ in validations)
        latest = max(frames for sr, frames in validations if sr == best)
        checkpoint = train.load_checkpoint(run / "best.pt")
        assert checkpoint["val_sr"] == pytest.approx(best, abs=0.01) and checkpoint["frames"] == latest

    # killed in the middle (after the third row's training finished) and run again: the same table
    runs_b = tmp_path / "b"
    proc = subprocess.Popen(
        _table_cmd(runs_b, runs_b), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env
    )
    deadline = time.time() + 120
    while proc.poll() is None and time.time() < deadline:
        if len(list(runs_b.glob("train/*/finished.json"))) >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (runs_b / "table1-smoke.md").exists()
    again = subprocess.run(_table_cmd(runs_b, runs_b), capture_output=True, text=True, env=env)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "nothing to do" in again.stdout  # the finished rows were not trained again
    assert _numbers((runs_b / "table1-smoke.md").read_text()) == _numbers(table_a)
    # all done on disk: rows found finished give no ETA, rather than "about 0 min left"
    third = subprocess.run(
        _table_cmd(tmp_path / "a", tmp_path / "a"), capture_output=True, text=True, env=env
    )
    assert third.returncode == 0 and "min left" not in third.stdout, third.stdout[-2000:]
    assert "min left" in whole.stdout  # while rows train, it is given


def test_table_errors_are_one_line(capsys, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace('method = "ff_a3c"', 'method = "ff_a4c"'))
    assert main(["table", "--spec", str(bad), "--runs", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "rows[2].method" in err and err.count("\n") == 1
    assert main(["table", "--preset", "huge", "--runs", str(tmp_path)]) == 2
    assert "unknown preset 'huge'" in capsys.readouterr().err
