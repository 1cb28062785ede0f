"""The checkpoints stage: every kept snapshot of a preset's finished runs evaluated into one CSV, any
checkpoint rule replayed from it, and its figure."""

from __future__ import annotations

import csv
import json
import math
import re

import cv2
import pytest
import torch

from kgnavbench.checkpoints import FIELDS, compared_at, read_csv, replay, row_curves, write_csv
from kgnavbench.cli import main
from kgnavbench.intervals import verdicts
from kgnavbench.table_spec import CELL_KEYS, SPEC_FILE, TableError, load_spec
from kgnavbench.table_statistics import EpisodeValue, RowResult, TableResult, table_statistics


@pytest.fixture(scope="module")
def trained(tmp_path_factory, hermetic_cache):
    """A smoke preset of one learned row that keeps a snapshot every 500 frames, trained (no table)."""
    tmp = tmp_path_factory.mktemp("checkpoints")
    text = SPEC_FILE.read_text()
    head, tail = text.split("[presets.smoke]\n", 1)
    smoke, rest = tail.split("\n\n", 1)
    smoke = smoke.replace('set = { threads = "1",', 'set = { threads = "1", keep_every = "500",')
    assert 'keep_every = "500"' in smoke
    spec = tmp / "spec.toml"
    spec.write_text(f'{head}[presets.smoke]\nrows = ["Random walk", "LSTM A3C"]\n{smoke}\n\n{rest}')
    runs = tmp / "runs"
    argv = ["table", "--spec", str(spec), "--preset", "smoke", "--runs", str(runs), "--train-only"]
    assert main(argv + ["--workers", "1"]) == 0
    (run,) = (runs / "train").iterdir()
    return spec, runs, run


def test_each_snapshot_is_one_line_and_the_rules_replay_the_trainers_picks(trained, tmp_path, capsys):
    spec, runs, run = trained
    out = tmp_path / "checkpoints.csv"
    png = tmp_path / "checkpoints.png"
    argv = ["checkpoints", "--spec", str(spec), "--preset", "smoke", "--runs", str(runs)]
    argv += ["--episodes", "1", "--csv", str(out), "--figure", str(png)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    snapshots = sorted(int(p.stem.split("-")[1]) for p in (run / "snapshots").glob("frames-*.pt"))
    assert len(snapshots) >= 2, snapshots
    lines = read_csv(out)
    assert [x["frames"] for x in lines] == snapshots
    assert {x["row"] for x in lines} == {"LSTM A3C"}  # the random walk keeps no snapshot: not a line
    assert f"{len(snapshots)} snapshots of 1 runs" in printed
    # long work says so: what it will evaluate, then each snapshot's time and what is left
    assert f"LSTM A3C seed 0: {len(snapshots)} snapshots of {run.name}, 1 episodes per target" in printed
    # (read back, when another test evaluated them first: no time left to say)
    assert re.search(rf"\(1/{len(snapshots)}, \d+ s(, about \S.* left for this run)?\)", printed), printed
    assert re.search(rf"\({len(snapshots)}/{len(snapshots)}, \d+ s\)", printed), printed
    with out.open() as f:
        assert tuple(csv.DictReader(f).fieldnames) == FIELDS
    # the validation SR is the trainer's, read from metrics.csv at the snapshot's frames
    with (run / "metrics.csv").open() as f:
        measured = {int(r["frames"]): float(r["val_sr"]) for r in csv.DictReader(f) if r["val_sr"]}
    for line in lines:
        assert line["val_sr"] == pytest.approx(measured[line["frames"]], abs=1e-4)
        assert line["seen_seen_static_episodes"] > 0 and 0 <= line["seen_seen_static_sr"] <= 100
        assert line["unseen_kitchens_static_episodes"] > 0  # FloorPlan13, the smoke's unseen kitchen
    # best.pt and last.pt are flagged, and replaying the rules from the CSV picks them
    best = torch.load(run / "best.pt", weights_only=True)["frames"]
    last = torch.load(run / "last.pt", weights_only=True)["frames"]
    assert [x["frames"] for x in lines if x["best"]] == [best]
    assert [x["frames"] for x in lines if x["last"]] == [last]
    assert replay(lines, "best")[run.name]["frames"] == best
    assert replay(lines, "last")[run.name]["frames"] == last
    assert replay(lines, "one-se")[run.name]["frames"] >= best  # the latest within one SE of the best
    # a second call re-evaluates nothing (the evaluations resume) and writes the same file
    before = out.read_bytes()
    evaluations = sorted(p.name for p in (runs / "eval").iterdir())
    assert main(argv) == 0
    assert out.read_bytes() == before
    assert sorted(p.name for p in (runs / "eval").iterdir()) == evaluations
    # a seed the preset does not train (it has one) is refused by name, the lines kept as they are
    assert main([*argv, "--seed", "1"]) == 2 and out.read_bytes() == before
    assert "preset 'smoke' trains seeds 0..0, not 1" in capsys.readouterr().err
    image = cv2.imread(str(png))
    assert image is not None and image.shape[0] > 300 and image.shape[1] > 600


def test_other_runs_lines_are_kept_and_a_bad_csv_is_named(tmp_path):
    line = {key: 0 for key in FIELDS} | {"row": "IL", "run": "imitation-0123456789", "val_sr": 12.5}
    other = line | {"run": "imitation-abcdefabcd", "seed": 1, "frames": 7, "val_sr": math.nan}
    path = tmp_path / "c.csv"
    write_csv(path, [line, other])
    back = read_csv(path)
    assert [x["run"] for x in back] == ["imitation-0123456789", "imitation-abcdefabcd"]
    assert back[0]["val_sr"] == 12.5 and math.isnan(back[1]["val_sr"])
    assert replay(back, "best") == {"imitation-0123456789": back[0]}  # no validation: no pick
    with pytest.raises(TableError, match="unknown checkpoint rule"):
        replay(back, "median")
    path.write_text(path.read_text().replace("12.5000", "twelve"))
    with pytest.raises(TableError, match=r"c\.csv, line 2: not a number"):
        read_csv(path)
    path.write_text("a,b\n1,2\n")
    with pytest.raises(TableError, match="not a checkpoints CSV"):
        read_csv(path)


def test_the_figure_draws_one_point_per_snapshot_of_the_schedule():
    """Seeds whose snapshots came at other frames (IL: an update ends where its episodes end) make one
    point per snapshot of the schedule, their mean, not one point per seed."""
    line = {key: math.nan for key in FIELDS} | {"row": "IL", "run": "imitation-0123456789"}
    lines = [
        line | {"seed": seed, "frames": frames, "seen_seen_static_sr": sr}
        for seed, frames, sr in (
            (0, 2_500_354, 4.0),
            (1, 2_500_237, 6.0),
            (0, 5_000_174, 3.0),
            (1, 5_000_800, 5.0),
        )
    ]
    curves = row_curves(lines, keep_every=2_500_000)
    assert list(curves) == ["seen kitchens, seen targets"]  # columns without a value are not drawn
    xs, ys = curves["seen kitchens, seen targets"]
    assert xs == pytest.approx([2.5002955, 5.000487]) and ys == [5.0, 4.0]


def test_ff_a3cs_validation_is_named_for_its_own_kitchens_in_the_figure():
    """FF A3C validates on its training kitchens' seen targets (its heads exist only there), the other
    rows on the validation kitchens: each panel's legend says which."""
    from kgnavbench.checkpoints import FF_VALIDATION_LEGEND, panel_series

    line = {key: math.nan for key in FIELDS} | {"seed": 0, "frames": 2_500_400, "val_sr": 8.3}
    ff = panel_series([line | {"row": "FF A3C", "run": "ff_a3c-0123456789"}], 2_500_000)
    lstm = panel_series([line | {"row": "LSTM A3C", "run": "lstm_a3c-0123456789"}], 2_500_000)
    assert list(ff) == [FF_VALIDATION_LEGEND] and ff[FF_VALIDATION_LEGEND][1] == [8.3]
    assert list(lstm) == ["validation (unseen kitchens)"]


def test_a_snapshot_stands_for_the_multiple_of_keep_every_it_was_kept_past():
    """The trainer keeps a snapshot at the first update past each multiple of keep_every: a smoke run's
    (500 apart) and the paper's (2.5M apart) map to their multiple whatever their offsets; runs kept
    at other spacings meet where their multiples do; without keep_every, the frames themselves."""
    from kgnavbench.checkpoints import snapshot_point

    assert [snapshot_point(f, 500) for f in (525, 1015, 517, 1030)] == [500, 1000, 500, 1000]
    assert [snapshot_point(f, 2_500_000) for f in (2_500_354, 5_000_800, 40_000_800)] == [
        2_500_000,
        5_000_000,
        40_000_000,
    ]
    assert snapshot_point(2_000_400, 2_000_000) != snapshot_point(2_500_400, 2_500_000)
    assert snapshot_point(10_000_400, 2_000_000) == snapshot_point(10_001_600, 2_500_000) == 10_000_000
    assert snapshot_point(1234, 0) == 1234


def test_an_unknown_row_is_refused_by_name(trained, capsys):
    spec, runs, _ = trained
    argv = ["checkpoints", "--spec", str(spec), "--preset", "smoke", "--runs", str(runs), "--row", "Nope"]
    assert main(argv) == 2
    assert "no row named 'Nope'" in capsys.readouterr().err
    # a row the preset does not train, or a seed it does not, is named: nothing evaluated or written
    csv_path = runs / "refused.csv"
    argv = [
        "checkpoints",
        "--spec",
        str(spec),
        "--preset",
        "smoke",
        "--runs",
        str(runs),
        "--csv",
        str(csv_path),
    ]
    assert main([*argv, "--row", "+KG"]) == 2
    assert "preset 'smoke' has no row '+KG'" in capsys.readouterr().err
    assert main([*argv, "--seed", "0", "--seed", "4"]) == 2
    assert "preset 'smoke' trains seeds 0..0, not 4" in capsys.readouterr().err
    assert not csv_path.exists()
    # a row with seeds of its own (`row_seeds`): its seeds are accepted, one beyond them refused
    more = spec.parent / "more-seeds.toml"
    more.write_text(
        spec.read_text().replace("[presets.smoke]\n", '[presets.smoke]\nrow_seeds = { "LSTM A3C" = 2 }\n')
    )
    argv[2] = str(more)
    assert main([*argv, "--row", "LSTM A3C", "--seed", "2"]) == 2
    assert "preset 'smoke' trains seeds 0..1 of LSTM A3C, not 2" in capsys.readouterr().err
    main([*argv, "--row", "LSTM A3C", "--seed", "1"])
    assert "skipped: row 'LSTM A3C' (seed 1): no finished" in capsys.readouterr().out  # none here


def test_two_rows_are_compared_at_the_same_frames(trained, tmp_path, capsys):
    """--matched: other - base at every snapshot both rows kept, per cell, with the interval Table I's
    comparisons get; with one seed a cell's difference is the two snapshots' SR apart."""
    spec, runs, _ = trained
    two = tmp_path / "spec.toml"
    text = spec.read_text()
    assert 'rows = ["Random walk", "LSTM A3C"]' in text
    two.write_text(text.replace('rows = ["Random walk", "LSTM A3C"]', 'rows = ["LSTM A3C", "+IL"]'))
    assert main(["table", "--spec", str(two), "--preset", "smoke", "--runs", str(runs), "--train-only"]) == 0
    out, png = tmp_path / "c.csv", tmp_path / "c.png"
    argv = ["checkpoints", "--spec", str(two), "--preset", "smoke", "--runs", str(runs), "--episodes", "1"]
    assert main([*argv, "--csv", str(out), "--figure", str(png), "--matched"]) == 0
    printed = capsys.readouterr().out
    assert "+IL - LSTM A3C:" in printed and "matched snapshots (1 and 1 seeds)" in printed
    lines = read_csv(out)
    with (tmp_path / "c-matched.csv").open() as f:
        pairs = list(csv.DictReader(f))
    assert {(p["other"], p["base"]) for p in pairs} == {("+IL", "LSTM A3C")}
    sr = {(x["row"], x["frames"]): x for x in lines}
    frames = sorted({x["frames"] for x in lines})
    assert sorted({int(p["frames"]) for p in pairs}) == frames  # both rows keep the same snapshots
    for p in pairs:
        if p["metric"] != "SR":
            continue
        key = p["cell"].replace("/", "_") + "_sr"
        expected = sr[("+IL", int(p["frames"]))][key] - sr[("LSTM A3C", int(p["frames"]))][key]
        assert float(p["difference"]) == pytest.approx(expected, abs=1e-3)
        assert float(p["low"]) <= float(p["difference"]) <= float(p["high"])
        assert p["verdict"] in verdicts(3)
    image = cv2.imread(str(tmp_path / "c-matched.png"))
    assert image is not None and image.shape[1] > 600
    # another pair's lines in the CSV are kept by a call that recomputes this one
    matched_csv = tmp_path / "c-matched.csv"
    other_pair = matched_csv.read_text().splitlines()[1].replace("LSTM A3C,+IL,", "+TSE,+IL+TSE,", 1)
    matched_csv.write_text(matched_csv.read_text() + other_pair + "\n")
    assert main([*argv, "--csv", str(out), "--matched"]) == 0
    assert matched_csv.read_text().count("+TSE,+IL+TSE,") == 1
    # --matched reads every finished seed: not with --seed or --unfinished
    assert main([*argv, "--csv", str(out), "--matched", "--seed", "0"]) == 2
    assert "not with --seed or --unfinished" in capsys.readouterr().err


def test_matched_pairs_the_seeds_snapshots_of_one_schedule_not_their_exact_frames(monkeypatch, tmp_path):
    """A snapshot is kept at the first update past each multiple of keep_every, so seeds (IL's
    episodes end where they end) keep it at other frames: they are paired as one snapshot, at their
    mean frames; one some seed lacks is named and left out."""
    from pathlib import Path

    from kgnavbench import checkpoints

    at = {  # (row, seed) -> the frames of its snapshots
        ("LSTM A3C", 0): [2_500_400, 5_000_800],
        ("LSTM A3C", 1): [2_500_013, 5_000_977],
        ("LSTM A3C", 2): [2_500_400, 5_000_800, 7_501_200],
        ("+IL", 0): [2_500_400, 5_000_800],
        ("+IL", 1): [2_500_400, 5_000_800],
        ("+IL", 2): [2_500_400, 5_000_800],
        ("+IL", 3): [2_500_400, 5_000_800],  # the paper preset's row_seeds: +IL has 4
    }
    monkeypatch.setattr(
        checkpoints, "run_with_snapshots", lambda p, row, seed, *a, **k: Path(f"{row.name}/{seed}")
    )

    def snapshots(snapshot_run):
        row, seed = snapshot_run.row, snapshot_run.seed
        return {f: f"{row.name} s{seed} at {f}" for f in at.get((row.name, seed), [])}

    calls = []
    monkeypatch.setattr(checkpoints.SnapshotRun, "episodes_by_frames", snapshots)
    monkeypatch.setattr(checkpoints, "run_keep_every", lambda run_dir: 2_500_000)
    monkeypatch.setattr(
        checkpoints,
        "compared_at",
        lambda b, be, o, oe, frames, margin: calls.append((b.name, be, oe, frames)) or [],
    )
    said = []
    checkpoints.matched(load_spec(SPEC_FILE), "paper", tmp_path, rows=("LSTM A3C",), progress=said.append)
    pairs = [c for c in calls if c[0] == "LSTM A3C"]
    assert [c[3] for c in pairs] == [  # the mean over both rows' 7 seeds
        round((2_500_400 * 6 + 2_500_013) / 7),
        round((5_000_800 * 6 + 5_000_977) / 7),
    ]
    assert pairs[0][1] == ["LSTM A3C s0 at 2500400", "LSTM A3C s1 at 2500013", "LSTM A3C s2 at 2500400"]
    assert pairs[1][2] == [f"+IL s{seed} at 5000800" for seed in range(4)]
    assert any("frames 7,501,200 left out" in line for line in said)


def test_a_matched_comparison_is_table_is_comparison_on_the_same_episodes():
    """compared_at's interval is the one Table I's comparison gives for the same episodes (each row's
    own bootstrap stream, differenced), with 3 and 2 seeds of made-up episodes."""
    import random

    spec = load_spec(SPEC_FILE)
    rows = {row.name: row for row in spec.rows}
    base, other = rows["+KG"], rows["+KG+Attention"]
    rng = random.Random(0)

    def seed_episodes(p: float) -> dict:
        cells = {cell: [] for cell in CELL_KEYS}
        for cell in ("seen_seen/static", "unseen_kitchens/static"):
            for target in range(6):
                for _ in range(4):
                    success = 100.0 * (rng.random() < p)
                    cells[cell].append(EpisodeValue(f"K/{target}", success, success * rng.random()))
        return cells

    base_seeds = [seed_episodes(0.3) for _ in range(3)]
    other_seeds = [seed_episodes(0.6) for _ in range(2)]
    lines = compared_at(base, base_seeds, other, other_seeds, 1000, spec.protocol.margin)
    table = TableResult(
        spec,
        spec.preset("paper"),
        [RowResult(base, base_seeds, [], [], 0.0), RowResult(other, other_seeds, [], [], 0.0)],
        0.0,
        "",
    )
    expected = {
        (c.cell, c.metric): c
        for c in table_statistics(table).comparisons
        if (c.comparison.base, c.comparison.other) == ("+KG", "+KG+Attention") and c.ours is not None
    }
    assert {(x["cell"], x["metric"]) for x in lines} == set(expected) and len(lines) == 4
    for x in lines:
        want = expected[(x["cell"], x["metric"])]
        assert (x["difference"], x["low"], x["high"]) == (want.ours.estimate, want.ours.low, want.ours.high)
        assert x["verdict"] == want.verdict and (x["base_seeds"], x["other_seeds"]) == (3, 2)
        paper = want.paper_difference
        assert math.isnan(x["paper_difference"]) if paper is None else x["paper_difference"] == paper


def test_a_run_whose_snapshots_are_gone_is_skipped_for_the_right_reason(tmp_path, monkeypatch):
    """A run trained with keep_every whose snapshots/ folder is empty is named as such, not as one
    trained without keep_every (which is said only where it is true)."""
    from kgnavbench import checkpoints

    said = []
    for keep_every, expected in (
        (2500, "though it trained with keep_every=2500"),
        (0, "trained without keep_every"),
    ):
        run_dir = tmp_path / f"run-{keep_every}"
        (run_dir / "snapshots").mkdir(parents=True)
        (run_dir / "config.json").write_text(json.dumps({"options": {"keep_every": str(keep_every)}}))
        monkeypatch.setattr(checkpoints, "find_trained", lambda *a, run_dir=run_dir, **k: run_dir)
        monkeypatch.setattr(checkpoints, "row_options", lambda preset, row: {})
        assert checkpoints.run_with_snapshots(None, None, 0, tmp_path, "cpu", said.append) is None
        assert said[-1].startswith(f"skipped: {run_dir} kept no snapshot") and expected in said[-1], said[-1]
