"""The table stage: the spec and its errors, the writers' text, and (smoke preset) the whole way from
training to the written table, resumed after a kill."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kgnavbench import runs
from kgnavbench.cli import build_parser, main
from kgnavbench.jobs import table_jobs, time_left
from kgnavbench.metrics import EpisodeResult
from kgnavbench.table_files import caption, to_ablation_csv, to_csv, to_latex, to_markdown, write_table
from kgnavbench.table_spec import (
    CELL_KEYS,
    CELLS,
    SPEC_FILE,
    Comparison,
    Preset,
    TableError,
    load_spec,
    parse_spec,
)
from kgnavbench.table_statistics import EpisodeValue, RowResult, TableResult, cell_episodes
from kgnavbench.zoo import same_job_runs

PAPER_ROWS = ["Random walk", "IL", "LSTM A3C", "FF A3C", "+IL", "+TSE", "+IL+TSE", "+KG", "+KG+Attention"]


def test_the_committed_spec_has_the_papers_rows_ours_presets_and_comparisons():
    spec = load_spec()
    names = [r.name for r in spec.rows]
    assert names[:9] == PAPER_ROWS
    assert names[9:] == [
        "IL, DAgger with a shortest-path teacher",
        "+IL+TSE, TSE (targets)",
        "+IL+TSE, object detections, no graph",
        "+KG+Attention, softmax over all nodes",
        "+KG, first reading",
        "+KG+Attention, first reading",
    ]
    assert {"smoke", "quick", "quick-all", "paper"} <= set(spec.presets)
    # quick: the paper's nine rows; quick-all: every row, under the same options (so it reuses quick's runs)
    quick, every = spec.presets["quick"], spec.presets["quick-all"]
    assert list(quick.rows) == PAPER_ROWS and every.rows == ()
    assert quick.options == every.options and quick.options["threads"] == "1"
    assert (quick.frames, quick.episodes, quick.seeds) == (every.frames, every.episodes, every.seeds)
    assert quick.unseen_target_kitchens == every.unseen_target_kitchens  # (and so quick's evaluations)
    assert quick.seeds >= 3 and quick.episodes >= 20 and quick.frames >= 2_000_000
    assert spec.presets["paper"].frames == 40_000_000 and spec.presets["paper"].episodes == 100
    assert spec.protocol.success_rule == "destination" and spec.protocol.stop_ends
    rows = {r.name: r for r in spec.rows}
    assert not rows["FF A3C"].unseen_kitchens
    # the paper's Table I as printed, five cells of [SPL, SR] per row; FF A3C has no unseen kitchens
    assert all(set(rows[name].paper) == set(CELL_KEYS) for name in PAPER_ROWS if name != "FF A3C")
    assert set(rows["FF A3C"].paper) == {"seen_seen/static", "seen_unseen/static", "seen_seen/actionable"}
    assert rows["+KG+Attention"].paper["seen_seen/static"] == (52.58, 98.44)
    assert rows["+KG+Attention"].paper["unseen_kitchens/static"] == (7.2, 41.09)
    assert rows["Random walk"].paper["unseen_kitchens/actionable"] == (0.08, 3.25)
    assert not rows["+IL+TSE, TSE (targets)"].paper
    assert spec.comparisons == (
        Comparison("LSTM A3C", "+IL"),
        Comparison("LSTM A3C", "+TSE"),
        Comparison("+IL", "+IL+TSE"),
        Comparison("+TSE", "+IL+TSE"),
        Comparison("+IL+TSE", "+KG"),
        Comparison("+KG", "+KG+Attention"),
        Comparison("+IL+TSE", "+IL+TSE, TSE (targets)"),
        Comparison("+KG+Attention, first reading", "+KG+Attention, softmax over all nodes"),
        Comparison("+KG, first reading", "+KG"),  # the two readings of the graph rows
        Comparison("+KG+Attention, first reading", "+KG+Attention"),
        Comparison("+IL+TSE, object detections, no graph", "+KG"),  # the graph's own effect
    )
    # the graph's control row gets the KG rows' detections and no graph; it runs in quick-all and paper
    control = rows["+IL+TSE, object detections, no graph"]
    assert control.method == "lstm_a3c"
    assert control.options == {"il": "true", "tse": "true", "detections": "true"}
    # the paper preset: the paper's nine rows and the control row (issue 25), in the paper's order
    assert list(spec.presets["paper"].rows) == [*PAPER_ROWS, "+IL+TSE, object detections, no graph"]
    # paper-last: the paper preset's runs, every row, tested with their last.pt; the same runs only
    # while every field that decides them is the paper preset's
    paper, last = spec.presets["paper"], spec.presets["paper-last"]
    assert last.checkpoint == "last" and paper.checkpoint == "" and set(last.rows) <= set(paper.rows)
    assert dataclasses.replace(last, name="paper", description="", rows=(), checkpoint="") == (
        dataclasses.replace(paper, description="", rows=())
    )
    # paper-visible: the paper preset's runs and evaluations, scored under the visible rule
    visible = spec.presets["paper-visible"]
    assert visible.score_rule == "visible" and paper.score_rule == ""
    assert dataclasses.replace(visible, name="paper", description="", score_rule="") == (
        dataclasses.replace(paper, description="")
    )


def test_the_paper_protocol_preset_trains_as_the_paper_states_and_its_twin_is_the_same_runs():
    """paper-protocol: the paper's own training protocol (no start curriculum, 5000-action episodes, a
    wrong Stop a no-op, 7 agents per kitchen: 140 threads with one target each, widths 128) over the
    paper preset's rows; paper-protocol-last the same runs with their last.pt. The options are read
    as the trainer resolves them, so that a default changed under the preset fails here too."""
    from kgnavbench.jobs import row_options
    from kgnavbench.plugins import load_plugin, make_config

    spec = load_spec(SPEC_FILE)
    protocol, last = spec.presets["paper-protocol"], spec.presets["paper-protocol-last"]
    paper = spec.presets["paper"]
    assert protocol.frames == 40_000_000 and protocol.episodes == 100 and protocol.seeds == 3
    assert list(protocol.rows) == list(paper.rows) and not protocol.train_kitchens
    rows = {r.name: r for r in spec.rows}
    row = rows["LSTM A3C"]
    resolved = make_config(load_plugin(row.method), row_options(protocol, row))
    assert resolved.start_curriculum == 0.0 and resolved.episode_cap == 5000
    assert resolved.stop_ends_from is None and "stop_ends_from" not in protocol.options
    assert resolved.wrong_stop_penalty == 0.0 and resolved.agents_per_kitchen == 7
    assert resolved.hidden == resolved.lstm == 128 and resolved.il_fraction == 0.05
    # everything else as the paper preset's
    differs = {
        k for k in {*protocol.options, *paper.options} if protocol.options.get(k) != paper.options.get(k)
    }
    assert differs == {"episode_cap", "start_curriculum", "stop_ends_from"}
    assert last.checkpoint == "last" and protocol.checkpoint == ""
    assert dataclasses.replace(last, name="paper-protocol", description="", checkpoint="") == (
        dataclasses.replace(protocol, description="")
    )


GOOD = SPEC_FILE.read_text()
# the paper presets' own seeds per row (the first: the paper preset's)
ROW_SEEDS = (
    'row_seeds = { "+IL" = 4, "+TSE" = 4, "+IL+TSE" = 5, "+KG" = 5, '
    '"+IL+TSE, object detections, no graph" = 5 }\n'
)
assert GOOD.count(ROW_SEEDS) == 3
A_COMPARISON = '[[comparisons]]\nbase = "+KG"\nother = "+KG+Attention"\n'
assert A_COMPARISON in GOOD


UNSEEN_TARGETS = '[presets.{0}]\nunseen_target_kitchens = ["{1}"]\n'


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (
            lambda t: t.replace('success_rule = "destination"', 'success_rule = "nearby"'),
            "protocol.success_rule",
        ),
        (lambda t: t.replace("seen_cap = 100", "seen_cap = 50"), "seen_cap/unseen_cap"),
        (
            lambda t: t.replace('success_rule = "destination"', 'success_rule = "arrival"'),
            "protocol: success_rule 'arrival' makes Stop a no-op: stop_ends must be false",
        ),
        (lambda t: t.replace("\nmargin = 3\n", "\nmargin = 5\n"), "protocol.margin = 5 must be 0..3 points"),
        (lambda t: t.replace("\nmargin = 3\n", "\nmargin = -1\n"), "protocol.margin = -1 must be 0..3"),
        (
            lambda t: t.replace("\nmargin = 3\n", '\nmargin = "3"\n'),
            "protocol.margin = '3' must be int or float",
        ),
        (lambda t: t.replace("stop_ends = true", 'stop_ends = "yes"'), "protocol.stop_ends"),
        (lambda t: t.replace('checkpoint = "best_val_sr"', 'checkpoint = "first"'), "protocol.checkpoint"),
        (
            lambda t: t.replace("[presets.smoke]\n", '[presets.smoke]\ncheckpoint = "best"\n'),
            "presets.smoke.checkpoint",
        ),
        (
            lambda t: t.replace('score_rule = "visible"', 'score_rule = "nearby"'),
            "presets.paper-visible.score_rule = 'nearby': the only other rule",
        ),
        (
            lambda t: t.replace("stop_ends = true", "stop_ends = false"),
            "presets.paper-visible.score_rule = 'visible': the only other rule",
        ),
        (lambda t: t.replace("frames = 2_000_000", "frames = -5"), "presets.quick.frames"),
        (lambda t: t.replace("frames = 2_000_000", 'frames = "lots"'), "presets.quick.frames"),
        (lambda t: t.replace("episodes = 20\n", "episodes = 101\n"), "presets.quick.episodes"),
        (lambda t: t.replace('train_kitchens = ["FloorPlan1"]', 'train_kitchens = ["Kitchen9"]'), "Kitchen9"),
        (lambda t: t.replace('method = "ff_a3c"', 'method = "ff_a4c"'), "rows[3].method"),
        (lambda t: t.replace('name = "IL"', 'name = "Random walk"'), "row name is used twice"),
        (lambda t: t.replace("[protocol]", "[protocol]\ncolour = 3"), "unknown field(s) colour"),
        (
            lambda t: t.replace(
                'method = "random_walk"\noptions = {}', 'method = "random_walk"\noptions = { x = [1] }'
            ),
            "rows[0].options.x",
        ),
        (
            lambda t: t + "\n[[rows]]\nname = 'x'\nmethod = 'oracle'\npaper = { 'seen_seen/static' = 3 }\n",
            "rows[15].paper.'seen_seen/static'",
        ),
        # the cell no target fills is not one of Table I's five
        (
            lambda t: (
                t
                + "\n[[rows]]\nname = 'x'\nmethod = 'oracle'\npaper = { 'seen_unseen/actionable' = [1, 2] }\n"
            ),
            "rows[15].paper.'seen_unseen/actionable'",
        ),
        # the random walk's numbers are in `paper` now: a note beside them is an unknown field
        (
            lambda t: t.replace('method = "random_walk"\n', 'method = "random_walk"\npaper_note = "1 / 2"\n'),
            "rows[0] has unknown field(s) paper_note",
        ),
        (
            lambda t: t.replace('base = "+KG"\n', 'base = "+GK"\n'),
            "comparisons[5].base = '+GK' is not a row name",
        ),
        (lambda t: t.replace('other = "+KG+Attention"\n', ""), "comparisons[5].other is missing"),
        (
            lambda t: t.replace('other = "+KG+Attention"\n', "other = 7\n"),
            "comparisons[5].other = 7 must be str",
        ),
        (
            lambda t: t.replace('other = "+KG+Attention"\n', 'other = "+KG"\n'),
            "comparisons[5]: base and other",
        ),
        (lambda t: t + "\n" + A_COMPARISON, "comparisons[11]: '+KG+Attention' against '+KG' is there twice"),
        (
            lambda t: t.replace('other = "+KG+Attention"\n', 'other = "+KG+Attention"\nwhy = 1\n'),
            "comparisons[5] has unknown field(s) why",
        ),
        (
            lambda t: "comparisons = 3\n" + t[: t.index("# The comparisons the paper draws")],
            "comparisons = 3 must be list",
        ),
        (lambda t: t.replace("[protocol]", "[protocol"), "not valid TOML"),
        (
            lambda t: t.replace('rows = ["Random walk", "IL",', 'rows = ["Random walk", "Il",'),
            "presets.quick.rows = ['Random walk', 'Il',",
        ),
        (
            lambda t: t.replace('rows = ["Random walk", "IL",', 'rows = ["Random walk", "Random walk",'),
            "a row is named twice",
        ),
        (lambda t: t.replace('rows = ["Random walk", "IL",', 'rows = "IL"\n#'), "presets.quick.rows = 'IL'"),
        (
            lambda t: t.replace("[presets.paper]\n", UNSEEN_TARGETS.format("paper", "FloorPlan99")),
            "presets.paper.unseen_target_kitchens: unknown kitchen 'FloorPlan99'",
        ),
        (
            lambda t: t.replace("[presets.paper]\n", UNSEEN_TARGETS.format("paper", "FloorPlan27")),
            "presets.paper.unseen_target_kitchens: FloorPlan27 is not a training kitchen that the preset",
        ),
        (
            lambda t: t.replace("[presets.smoke]\n", UNSEEN_TARGETS.format("smoke", "FloorPlan2")),
            "presets.smoke.unseen_target_kitchens: FloorPlan2 is not a training kitchen that the preset",
        ),
        (
            lambda t: t.replace(ROW_SEEDS, 'row_seeds = { "+KG" = 0 }\n', 1),
            "presets.paper.row_seeds.'+KG' = 0 must be a number of seeds, 1..100",
        ),
        (
            lambda t: t.replace(ROW_SEEDS, 'row_seeds = { "+KG" = true }\n', 1),
            "presets.paper.row_seeds.'+KG' = True must be a number of seeds",
        ),
        (
            lambda t: t.replace(ROW_SEEDS, 'row_seeds = { "+GK" = 6 }\n', 1),
            "presets.paper.row_seeds: '+GK' is not a row of the preset",
        ),
        # a row of the spec that the preset does not run
        (
            lambda t: t.replace(ROW_SEEDS, 'row_seeds = { "+KG, first reading" = 6 }\n', 1),
            "presets.paper.row_seeds: '+KG, first reading' is not a row of the preset",
        ),
    ],
)
def test_a_bad_spec_gets_one_clear_line_naming_the_field(change, named):
    bad = change(GOOD)
    assert bad != GOOD
    with pytest.raises(TableError, match=None) as e:
        parse_spec(bad, "tables/bad.toml")
    message = str(e.value)
    assert "\n" not in message and "tables/bad.toml" in message and named in message, message


def test_a_preset_can_evaluate_unseen_targets_in_some_kitchens_and_its_caption_says_so():
    listed = '[presets.paper]\nunseen_target_kitchens = ["FloorPlan3", "FloorPlan1"]\n'
    spec = parse_spec(GOOD.replace("[presets.paper]\n", listed))
    preset = spec.presets["paper"]
    assert preset.unseen_target_kitchens == ("FloorPlan1", "FloorPlan3")  # in the kitchens' order
    result = TableResult(spec, preset, [], 60.0, "abc")
    assert (
        "seen or unseen targets (unseen targets in 2 of the training kitchens: FloorPlan1, FloorPlan3);"
        in (caption(result))
    )
    assert "seen or unseen targets; '–'" in caption(TableResult(spec, spec.presets["smoke"], [], 60.0, "abc"))


def test_a_row_can_have_its_own_seeds_which_follow_every_other_job_and_the_caption_says_so():
    more = 'row_seeds = { "+KG" = 5, "IL" = 4 }\n'
    spec = parse_spec(GOOD.replace(ROW_SEEDS, more, 1))
    preset, before = spec.presets["paper"], parse_spec(GOOD.replace(ROW_SEEDS, "", 1)).presets["paper"]
    assert (preset.seeds_of("+KG"), preset.seeds_of("IL"), preset.seeds_of("FF A3C")) == (5, 4, 3)
    jobs = [(row.name, seed) for row, seed in table_jobs(spec, preset)]
    # the preset's seeds of every row first, in the old order; then the extra seeds, row by row in the
    # spec's order: adding seeds renumbers none of the first seeds' jobs
    old = [(row.name, seed) for row, seed in table_jobs(spec, before)]
    assert len(old) == 30  # the paper preset's ten rows, 3 seeds each
    assert jobs[: len(old)] == old
    assert jobs[len(old) :] == [("IL", 3), ("+KG", 3), ("+KG", 4)]
    assert "3 seeds (+KG: 5; IL: 4);" in caption(TableResult(spec, preset, [], 60.0, "abc"))
    # a row's own seeds are more than the preset's: fewer, or as many, is refused by name
    for n in (2, 3):
        with pytest.raises(TableError, match=f"'LSTM A3C' = {n} is not more than the preset's seeds = 3"):
            parse_spec(GOOD.replace(ROW_SEEDS, f'row_seeds = {{ "LSTM A3C" = {n} }}\n', 1))
    # presets whose rows have other seeds are other runs: no paired difference between them
    from kgnavbench.table_statistics import check_same_runs

    with pytest.raises(TableError, match="differ in row_seeds"):
        check_same_runs(preset, spec.presets["paper-last"])


def test_a_spec_without_a_margin_has_none():
    assert parse_spec(GOOD.replace("\nmargin = 3\n", "\n")).protocol.margin == 0.0
    assert parse_spec(GOOD).protocol.margin == 3.0


def test_a_spec_without_comparisons_is_fine():
    text = GOOD[: GOOD.index("# The comparisons the paper draws")]
    assert "[[comparisons]]" not in text and parse_spec(text).comparisons == ()


def test_a_missing_spec_file():
    with pytest.raises(TableError, match="nope.toml"):
        load_spec("nope.toml")


def test_time_left_per_kind_of_row():
    # before any trained row is done, a random walk's seconds say nothing about the rows to come
    assert time_left([], [False, True, True]) is None
    assert time_left([(False, 2.0)], [True, True]) is None
    # then the mean of each kind times the rows of that kind to come
    assert time_left([(False, 2.0), (True, 60.0), (True, 120.0)], [True, False]) == 90.0 + 2.0
    assert time_left([(True, 60.0)], []) == 0.0


# ----------------------------------------------------------------------------------------------------
# the writers, on a table built by hand from episodes


def episode(column, kind, target, success, path=10, shortest=10, kitchen="FloorPlan1"):
    return EpisodeResult(
        kitchen=kitchen,
        target=target,
        kind=kind,
        column=column,
        start=0,
        max_steps=100,
        success=success,
        path_length=path,
        shortest_path=shortest,
        collisions=0,
        last_view_shows_target=success,
        episode_length=path + 1,
    )


def test_cell_episodes_keep_target_success_and_spl_term_in_percent():
    cells = cell_episodes(
        [
            episode("seen_seen", "static", "Apple|1", True, path=20, shortest=10),
            episode("seen_seen", "static", "Apple|1", False),
            episode("unseen_kitchens", "actionable", "Egg|2", True, kitchen="FloorPlan30"),
            episode("validation", "static", "Cup|3", True),  # no cell of Table I
        ]
    )
    assert list(cells) == list(CELL_KEYS)
    assert cells["seen_seen/static"] == [
        EpisodeValue("FloorPlan1/Apple|1", 100.0, 50.0),
        EpisodeValue("FloorPlan1/Apple|1", 0.0, 0.0),
    ]
    assert cells["unseen_kitchens/actionable"] == [EpisodeValue("FloorPlan30/Egg|2", 100.0, 100.0)]
    assert cells["seen_unseen/static"] == [] and sum(len(v) for v in cells.values()) == 3


def fake_result(preset_name: str = "quick") -> TableResult:
    """Two seeds of four rows, episodes chosen so every interval can be worked out by hand.

    +KG+Attention, static seen/seen: seed 0 has target A (2 episodes, both succeed on a shortest path)
    and target B (2, both fail): SR 50, SPL 50, whatever the episode resample (within targets); seed 1
    succeeds on all 4 at twice the shortest path: SR 100, SPL 50. So SPL is 50 [50, 50]; SR's replicates
    are 50, 75 or 100 (seeds drawn with replacement, each end with p = 1/4): 75 [50, 100].
    +KG fails them all: 0 [0, 0]. Static unseen kitchens: both rows succeed on every episode (paths
    shortest): 100 [100, 100]. FF A3C: seen/seen static only. The last row is ours, not the paper's."""
    spec = load_spec()
    rows = {r.name: r for r in spec.rows}
    ss, uk = ("seen_seen", "static"), ("unseen_kitchens", "static")
    attention = [
        [
            episode(*ss, "A", True),
            episode(*ss, "A", True),
            episode(*ss, "B", False),
            episode(*ss, "B", False),
        ],
        [episode(*ss, t, True, path=20) for t in "AABB"],
    ]
    kg = [[episode(*ss, t, False) for t in "AABB"] for _ in range(2)]
    unseen = [episode(*uk, t, True, kitchen="FloorPlan30") for t in "CCD"]
    ff = [[episode(*ss, t, True, path=40) for t in "AB"] for _ in range(2)]

    def row(name, per_seed):
        return RowResult(
            rows[name], [cell_episodes(results) for results in per_seed], ["r"] * 2, ["e"] * 2, 1
        )

    return TableResult(
        spec=dataclasses.replace(spec, comparisons=(Comparison("+KG", "+KG+Attention"),)),
        preset=Preset(preset_name, "a test", 1000, 2, 2, (), (), {}),
        rows=[
            row("FF A3C", ff),
            row("+KG", [seed + unseen for seed in kg]),
            row("+KG+Attention", [seed + unseen for seed in attention]),
            row("+IL+TSE, TSE (targets)", ff),
        ],
        seconds=90.0,
        git_revision="abc123",
    )


@pytest.mark.parametrize(
    ("rule", "score_rule", "says", "never"),
    [
        ("destination", "", "success = Stop at the destination, Stop ends", "target visible"),
        ("visible", "", "success = Stop with the target visible, Stop ends", "at the destination"),
        (
            "arrival",
            "",
            "success = arriving at the destination (Zhu et al.'s rule), Stop is a no-op",
            "Stop at",
        ),
        ("destination", "visible", "evaluations run under Stop at the destination, scored", "arriving"),
    ],
)
def test_a_caption_and_a_paired_intro_name_the_rule_the_episodes_were_scored_under(
    rule, score_rule, says, never
):
    """The caption, and the paired tables' intro, name the spec's success rule (or the preset's score
    rule) as evaluate.SUCCESS_RULE_TEXT words it: never another rule's words."""
    from kgnavbench.table_paired import paired_intro

    result = fake_result()
    protocol = dataclasses.replace(result.spec.protocol, success_rule=rule, stop_ends=rule != "arrival")
    result = dataclasses.replace(
        result,
        spec=dataclasses.replace(result.spec, protocol=protocol),
        preset=dataclasses.replace(result.preset, score_rule=score_rule),
    )
    text = caption(result)
    assert says in text and never not in text.split("success = ")[1].split(";")[0], text
    intro = paired_intro(result, result)
    scored = score_rule or rule
    words = {"destination": "Stop at the destination", "visible": "Stop with the target visible"}
    assert f"success: {words.get(scored, 'arriving at the destination')}" in intro, intro


def test_a_paired_difference_is_episode_by_episode_and_refuses_other_runs_or_episodes():
    """`paired_differences`: a table minus another of the same runs and episodes (the final weights
    against the rule's checkpoint): each episode's value minus the same episode's, so a row whose every
    episode moves from failure to success differs by exactly +100 [100, 100] (higher), an unchanged one
    by 0 [0, 0] (no difference beyond the margin); a preset of other runs, or other episodes, is refused."""
    from kgnavbench.table_paired import to_paired_csv, to_paired_markdown
    from kgnavbench.table_statistics import paired_differences

    base = fake_result()
    result = fake_result()
    result.preset = dataclasses.replace(result.preset, name="quick-last", checkpoint="last")
    kg = next(r for r in result.rows if r.row.name == "+KG")
    kg.episodes = [
        {cell: [e._replace(success=100.0) for e in values] for cell, values in seed.items()}
        for seed in kg.episodes
    ]
    diffs = {(d.row, d.cell, d.metric): d for d in paired_differences(result, base)}
    assert len(diffs) == 4 * 5 * 2
    moved = diffs[("+KG", "seen_seen/static", "SR")]
    assert (moved.ours.estimate, moved.ours.low, moved.ours.high, moved.verdict) == (100, 100, 100, "higher")
    same = diffs[("+KG+Attention", "seen_seen/static", "SR")]
    assert (same.ours.estimate, same.ours.low, same.ours.high) == (0, 0, 0)
    assert same.verdict == "no difference beyond 3"
    assert diffs[("+KG", "unseen_kitchens/static", "SR")].ours.estimate == 0  # its successes stayed
    assert diffs[("FF A3C", "unseen_kitchens/static", "SR")].ours is None  # no episodes: '–'
    md = to_paired_markdown(result, base, list(diffs.values()))
    assert "preset 'quick-last' (last.pt: the final weights; success: Stop at the destination)" in md
    assert "| +KG | +100.0 [+100.0, +100.0] higher |" in md
    rows = list(csv.DictReader(to_paired_csv(result, base, list(diffs.values())).splitlines()[1:]))
    assert len(rows) == 40
    assert {r["verdict"] for r in rows} <= {"higher", "lower", "no difference beyond 3", "cannot tell", ""}
    assert "margin of 3 points" in md
    other_runs = fake_result()
    other_runs.preset = dataclasses.replace(other_runs.preset, frames=2000)
    with pytest.raises(TableError, match="differ in frames: not the same runs"):
        paired_differences(other_runs, base)
    kg.episodes[0]["seen_seen/static"] = kg.episodes[0]["seen_seen/static"][1:]
    with pytest.raises(TableError, match="episodes differ"):
        paired_differences(result, base)


def _cells_of(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def test_the_markdown_shows_intervals_the_papers_numbers_and_the_ablation_check():
    md = to_markdown(fake_result())
    assert "preset 'quick'" in md and "1,000 training frames" in md and "2 of the 100 fixed episodes" in md
    assert "mean over 2 seeds, 95% stratified bootstrap interval over seeds and episodes" in md
    assert "Git abc123" in md and "1.5 min" in md
    lines = {_cells_of(line)[0]: _cells_of(line) for line in md.splitlines() if line.startswith("| ")}
    head = lines["method"]
    assert head[1:3] == ["static seen/seen SPL", "static seen/seen SR"]
    assert head[-2:] == ["actionable unseen kitchens SPL", "actionable unseen kitchens SR"]
    assert len(head) == 1 + 2 * 5  # five cells, SPL and SR each
    # ours: mean over seeds [95% interval]; SPL first, as the paper
    attention = lines["+KG+Attention"]
    assert attention[1:3] == ["50.0 [50.0, 50.0]", "75.0 [50.0, 100.0]"]
    assert attention[5:7] == ["100.0 [100.0, 100.0]"] * 2
    assert attention[3:5] == ["–"] * 2 and attention[7:] == ["–"] * 4  # no episodes there
    # the paper's numbers as printed, on the line below
    paper = lines["+KG+Attention (paper)"]
    assert paper[1:] == [
        "52.58",
        "98.44",
        "14.89",
        "44.25",
        "7.20",
        "41.09",
        "38.51",
        "88.78",
        "5.26",
        "21.13",
    ]
    assert lines["FF A3C"][1:3] == ["25.0 [25.0, 25.0]", "100.0 [100.0, 100.0]"]  # L / P = 10 / 40
    assert lines["FF A3C (paper)"][5:7] == ["–", "–"]  # no FF A3C model for unseen kitchens
    assert lines["+IL+TSE, TSE (targets) (paper)"][1:] == ["–"] * 10  # our row: none in the paper
    # the ablation check: +KG+Attention - +KG per cell, SPL then SR: paper, ours, verdict
    rows = [_cells_of(line) for line in md.splitlines() if line.startswith("| +KG+Attention − +KG |")]
    checks = {row[1]: row for row in rows}
    assert len(rows) == len(checks) == 5
    assert "comparison" in lines and "**Ablation check.**" in md
    # the paper: 52.58 - 52.32 = +0.26 and 98.44 - 98.47 = -0.03, under half a point: no side to agree
    # with, so ours alone (+50, +75: higher)
    assert checks["static seen/seen"][2:] == [
        "+0.26",
        "+50.0 [+50.0, +50.0]",
        "higher",
        "-0.03",
        "+75.0 [+50.0, +100.0]",
        "higher",
    ]
    # 41.09 - 32.56 = +8.53; ours 0 [0, 0], within the spec's margin of 3 points: no difference
    assert checks["static unseen kitchens"][5:] == ["+8.53", "+0.0 [+0.0, +0.0]", "no difference beyond 3"]
    assert checks["static seen/unseen"][2:] == ["+0.79", "–", "–", "+2.30", "–", "–"]  # no episodes
    counts = (
        "0 holds; 0 holds, smaller than the paper's; 0 holds, larger than the paper's; 0 reversed; 1 higher; "
        "0 lower; 1 no difference beyond 3; 0 smaller than the paper's; 0 cannot tell"
    )
    assert f"Verdicts: SPL: {counts}. SR: {counts}." in md
    assert "at a margin of 3 points" in md


def _csv_rows(text: str) -> list[dict]:
    lines = text.splitlines()
    assert lines[0].startswith('"# ')  # the caption first, as a comment line
    return list(csv.DictReader(lines[1:]))


def test_the_csv_is_tidy_with_each_seeds_value_and_no_nan():
    result = fake_result()
    text = to_csv(result)
    rows = _csv_rows(text)
    assert list(rows[0]) == [
        "row",
        "method",
        "column",
        "kind",
        "metric",
        "mean",
        "ci_low",
        "ci_high",
        "paper",
        "episodes_per_seed",
        "seed_0",
        "seed_1",
    ]
    assert len(rows) == 4 * 5 * 2 and "nan" not in text.lower()
    cell = {(r["row"], r["column"], r["kind"], r["metric"]): r for r in rows}
    sr = cell[("+KG+Attention", "seen_seen", "static", "SR")]
    assert sr == {
        "row": "+KG+Attention",
        "method": "kg_attention",
        "column": "seen_seen",
        "kind": "static",
        "metric": "SR",
        "mean": "75",
        "ci_low": "50",
        "ci_high": "100",
        "paper": "98.44",
        "episodes_per_seed": "4",
        "seed_0": "50",
        "seed_1": "100",
    }
    assert cell[("+KG+Attention", "unseen_kitchens", "static", "SR")]["paper"] == "41.09"
    empty = cell[("FF A3C", "unseen_kitchens", "static", "SPL")]
    assert [empty[k] for k in ("mean", "ci_low", "ci_high", "paper", "seed_0", "seed_1")] == [""] * 6
    assert empty["episodes_per_seed"] == "0"
    assert [(r["column"], r["kind"]) for r in rows[:10:2]] == list(CELLS)


def test_the_ablation_csv():
    rows = _csv_rows(to_ablation_csv(fake_result()))
    assert len(rows) == 1 * 5 * 2  # one comparison, five cells, two metrics
    by = {(r["column"], r["kind"], r["metric"]): r for r in rows}
    sr = by[("seen_seen", "static", "SR")]
    assert (sr["base"], sr["other"], sr["paper_base"], sr["paper_other"]) == (
        "+KG",
        "+KG+Attention",
        "98.47",
        "98.44",
    )
    assert (sr["paper_difference"], sr["difference"], sr["ci_low"], sr["ci_high"]) == (
        "-0.03",
        "75",
        "50",
        "100",
    )
    assert sr["verdict"] == "higher"  # the paper: -0.03, no side
    unseen = by[("unseen_kitchens", "static", "SR")]
    assert (unseen["paper_difference"], unseen["difference"], unseen["verdict"]) == (
        "8.53",
        "0",
        "no difference beyond 3",
    )
    nothing = by[("seen_unseen", "static", "SR")]
    assert (nothing["paper_difference"], nothing["difference"], nothing["verdict"]) == ("2.3", "", "")


def test_the_latex_has_both_tables():
    tex = to_latex(fake_result())
    assert tex.count(r"\begin{table*}") == 2 and tex.count(r"\end{tabular}") == 2
    assert r"+KG+Attention & 50.0 [50.0, 50.0] & 75.0 [50.0, 100.0]" in tex
    assert r"+KG+Attention (paper) & 52.58 & 98.44 & 14.89 & 44.25 & 7.20 & 41.09" in tex
    # numbers get a math minus, names keep their hyphens; TeX's specials are escaped
    check = r"+KG+Attention $-$ +KG & static seen/seen & +0.26 & +50.0 [+50.0, +50.0] & higher & $-$0.03"
    assert check in tex
    assert (
        r"95\% stratified bootstrap" in tex
        and "FF A3C (paper) & 35.16 & 88.33 & 10.81 & 35.64 & -- & --" in tex
    )
    table, ablation = tex.split(r"\end{table*}")[:2]
    lines = [line for line in table.splitlines() if line.endswith("\\\\") and "multicolumn" not in line]
    assert len(lines) == 1 + 2 * 4 and all(line.count("&") == 2 * len(CELLS) for line in lines)
    lines = [line for line in ablation.splitlines() if line.endswith("\\\\") and "multicolumn" not in line]
    assert len(lines) == 1 + 5 and all(line.count("&") == 2 + 3 * 2 - 1 for line in lines)


def test_write_table_writes_four_files(tmp_path):
    paths = write_table(fake_result(), tmp_path)
    assert [p.name for p in paths] == ["table1.md", "table1.csv", "table1-ablation.csv", "table1.tex"]
    assert "98.44" in paths[0].read_text() and "41.09" in paths[1].read_text()
    paths = write_table(fake_result("smoke"), tmp_path)
    assert [p.name for p in paths] == [
        "table1-smoke.md",
        "table1-smoke.csv",
        "table1-smoke-ablation.csv",
        "table1-smoke.tex",
    ]
    assert all(p.stat().st_size > 300 for p in paths)
    # the same table again from another revision: the files differ only in the caption's provenance, and
    # are kept as they were (a committed table rewritten from its archive leaves the tree clean)
    again = dataclasses.replace(fake_result("smoke"), git_revision="f" * 40 + "-dirty", seconds=999.0)
    before = {p: p.read_text() for p in paths}
    kept = write_table(again, tmp_path)
    assert list(kept) == paths and kept.kept == paths and {p: p.read_text() for p in paths} == before
    assert "kept" in kept.summary() and "wrote" not in kept.summary()
    other = dataclasses.replace(again, preset=dataclasses.replace(again.preset, description="another"))
    changed = write_table(other, tmp_path)
    assert not changed.kept and "another" in paths[0].read_text() and "ffffffff" in paths[0].read_text()


# ----------------------------------------------------------------------------------------------------
# the smoke preset end to end: train, select, evaluate, write; killed and resumed


def _table_cmd(runs, out, workers: int = 1) -> list[str]:
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
        "--workers",
        str(workers),
    ]


def _numbers(markdown: str) -> list[str]:
    """The table's lines without the caption (which holds the wall time)."""
    return [line for line in markdown.splitlines() if line.startswith("| ")]


def test_smoke_table_end_to_end_and_resumed_after_a_kill(tmp_path, hermetic_cache, smoke_table):
    env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache)}
    # two jobs at a time in worker processes (the session's smoke table); the killed and resumed table
    # below runs one at a time and must come out the same (the preset fixes torch's threads)
    a, whole = smoke_table
    assert whole.returncode == 0, whole.stderr[-2000:]
    table_a = (a / "table1-smoke.md").read_text()
    for suffix in (".csv", "-ablation.csv", ".tex"):
        assert (a / f"table1-smoke{suffix}").stat().st_size > 500
    rows = _numbers(table_a)
    spec = load_spec()
    # the table (a header, ours and the paper's per row), the ablation check (a header, 5 cells each)
    assert len(rows) == 1 + 2 * len(spec.rows) + 1 + len(CELLS) * len(spec.comparisons)
    assert all(f"| {name} |" in table_a for name in ("IL", "+KG+Attention")) and "| 98.44 |" in table_a
    assert "preset 'smoke'" in table_a and "Git " in table_a

    # the checkpoint rule: best.pt is the validation with the best SR, the latest on a tie
    for run in (a / "train").iterdir():
        lines = list(csv.DictReader((run / "metrics.csv").read_text().splitlines()))
        validations = [(float(r["val_sr"]), int(r["frames"])) for r in lines if r["val_sr"]]
        best = max(sr for sr, _ in validations)
        latest = max(frames for sr, frames in validations if sr == best)
        checkpoint = runs.load_checkpoint(run / "best.pt")
        assert checkpoint["val_sr"] == pytest.approx(best, abs=0.01) and checkpoint["frames"] == latest

    # killed in the middle and run again: the same table. Half the runs are the first table's, finished
    # (as a killed table leaves the runs it finished); the others train here, one job at a time, and the
    # table is killed when the first of them has finished
    runs_b = tmp_path / "b"
    trained = sorted((a / "train").iterdir())
    for run in trained[: len(trained) // 2]:
        shutil.copytree(run, runs_b / "train" / run.name)
    proc = subprocess.Popen(
        _table_cmd(runs_b, runs_b), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env
    )
    deadline = time.time() + 120
    while proc.poll() is None and time.time() < deadline:
        if len(list(runs_b.glob("train/*/finished.json"))) > len(trained) // 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (runs_b / "table1-smoke.md").exists()
    again = subprocess.run(_table_cmd(runs_b, runs_b), capture_output=True, text=True, env=env)
    assert again.returncode == 0, again.stderr[-2000:]
    assert "nothing to do" in again.stdout  # the finished rows were not trained again
    assert _numbers((runs_b / "table1-smoke.md").read_text()) == _numbers(table_a)
    # all done on disk: rows found finished give no ETA, rather than "about 0 min left" (in the resumed
    # table's folder: the session's smoke table is only read, since other tests may read it meanwhile)
    third = subprocess.run(_table_cmd(runs_b, runs_b), capture_output=True, text=True, env=env)
    assert third.returncode == 0 and "min left" not in third.stdout, third.stdout[-2000:]
    assert "min left" in whole.stdout  # while rows train, it is given


def test_train_only_then_a_zoo_of_older_code_evaluates_without_training(tmp_path, capsys, monkeypatch):
    """`--train-only` trains the preset's runs and writes no table; `--trained ZOO` takes finished runs
    from a flat folder (as zoo/ ships them), matched by their options and not by the code that trained
    them, evaluates them without training and writes the table a plain `table` writes; `--archive`
    keeps its evaluations packed, from which a fresh runs folder assembles it without evaluating; a run
    missing from the zoo is one line naming the row and seed, never trained."""
    # the smoke preset with two rows, one that trains
    text = SPEC_FILE.read_text()
    head, tail = text.split("[presets.smoke]\n", 1)
    body, rest = tail.split("[presets.quick]\n", 1)
    rows = 'rows = ["Random walk", "LSTM A3C"]\n'
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(
        f"{head}[presets.smoke]\n{rows}{body}"
        f'[presets.smoke-visible]\nscore_rule = "visible"\n{rows}{body}'
        f'[presets.smoke-last]\ncheckpoint = "last"\n{rows}{body}[presets.quick]\n{rest}'
    )  # smoke-visible: the smoke preset's evaluations under the visible rule, as paper-visible is;
    # smoke-last: its runs' final weights, as paper-last
    smoke = ["table", "--spec", str(spec_path), "--preset", "smoke", "--workers", "1"]
    trained = tmp_path / "trained"
    assert main(smoke + ["--runs", str(trained), "--train-only"]) == 0
    out = capsys.readouterr().out
    assert "evaluates what is left and assembles" in out
    # the follow-up command as printed: this spec, these runs, and options the command takes
    then = shlex.split(out.split("then `")[1].split("`")[0])
    assert then[:2] == ["kgnavbench", "table"] and then[then.index("--spec") + 1] == str(spec_path)
    build_parser().parse_args(then[1:])
    assert not (trained / "eval").exists() and not list(tmp_path.rglob("table1-smoke.md"))
    assert len(list((trained / "train").glob("*/finished.json"))) == 1

    # the zoo: the same runs shipped (weights only), as if trained by an older revision of the code
    zoo = tmp_path / "zoo"
    for run in (trained / "train").iterdir():
        assert main(["ship", str(run), "--zoo", str(zoo)]) == 0
        assert f"shipped {zoo / run.name}" in capsys.readouterr().out
        assert sorted(p.name for p in (zoo / run.name).iterdir()) == [
            "best.pt", "best.pt.sha256", "config.json", "finished.json", "metrics.csv"
        ]  # fmt: skip
        shipped_ck = runs.load_checkpoint(zoo / run.name / "best.pt")
        assert list(shipped_ck) == list(runs.POLICY_KEYS)  # no optimiser, generators or agents
        config = json.loads((zoo / run.name / "config.json").read_text())
        config["training_code_sha256"], config["git_revision"] = "0" * 64, "0123456789abcdef"
        (zoo / run.name / "config.json").write_text(json.dumps(config))
    # what a killed ship leaves: a hidden staging folder with the run's JSON files and no weights
    run = next(zoo.iterdir())
    leftover = zoo / f".{run.name}-killed.tmp"
    leftover.mkdir()
    for name in ("config.json", "finished.json"):
        shutil.copyfile(run / name, leftover / name)
    shipped = tmp_path / "shipped"
    assert main(smoke + ["--runs", str(shipped), "--out", str(shipped), "--trained", str(zoo)]) == 0
    out = capsys.readouterr().out
    # one line for all the runs trained by other code, per revision
    assert (
        out.count("trained by other training code") == 1
        and "0123456789ab (" in out
        and "used as shipped" in out
    )
    assert not (shipped / "train").exists()  # nothing trained
    # the same table as the runs' own folder assembles (it evaluates them there, training nothing)
    assert main(smoke + ["--runs", str(trained), "--out", str(trained)]) == 0
    assert "nothing to do" in capsys.readouterr().out
    assert _numbers((shipped / "table1-smoke.md").read_text()) == _numbers(
        (trained / "table1-smoke.md").read_text()
    )
    # `--archive`: each evaluation is packed there (as tables/episodes/paper keeps Table I's), and a
    # fresh runs folder then assembles the same table from the archive, evaluating nothing
    archive = tmp_path / "archive"
    assert main(smoke + ["--runs", str(shipped), "--trained", str(zoo), "--archive", str(archive)]) == 2
    assert "no such folder (create it to start an archive)" in capsys.readouterr().err  # a typo, not hours
    archive.mkdir()
    assert (
        main(
            smoke
            + [
                "--runs",
                str(shipped),
                "--out",
                str(shipped),
                "--trained",
                str(zoo),
                "--archive",
                str(archive),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert sorted(p.name for p in archive.iterdir()) == sorted(
        f"{p.name}.tar.xz" for p in (shipped / "eval").iterdir()
    )
    assert out.count("packed ") == 2, out
    fresh = tmp_path / "fresh"
    # a read-only checkout assembles from its archive (faked: the suite may run as root, whom no
    # permission stops): the archive is used, never written
    real_access = os.access

    def access(path, mode, *args, **kwargs):
        if mode & os.W_OK and Path(path).resolve() == archive.resolve():
            return False
        return real_access(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", access)
    kept = {p.name: p.read_bytes() for p in archive.iterdir()}
    assert (
        main(
            smoke
            + ["--runs", str(fresh), "--out", str(fresh), "--trained", str(zoo), "--archive", str(archive)]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "agent-steps/s" not in out and "packed " not in out, out  # nothing evaluated, nothing packed again
    assert (
        f"--archive {archive}: read-only" in out
        and {p.name: p.read_bytes() for p in archive.iterdir()} == kept
    )
    monkeypatch.setattr(os, "access", real_access)
    assert _numbers((fresh / "table1-smoke.md").read_text()) == _numbers(
        (shipped / "table1-smoke.md").read_text()
    )
    assert main(smoke + ["--runs", str(fresh), "--train-only", "--archive", str(archive)]) == 2
    assert "--archive keeps evaluations; --train-only runs none" in capsys.readouterr().err
    # `--against`: the same runs' table under another rule, differenced episode by episode
    against = ["--runs", str(fresh), "--out", str(fresh), "--trained", str(zoo), "--archive", str(archive)]
    assert main(smoke + against + ["--preset", "smoke-visible", "--against", "smoke"]) == 0
    out = capsys.readouterr().out
    assert "agent-steps/s" not in out and "Paired difference: preset 'smoke-visible'" in out, out
    paired = (fresh / "table1-smoke-visible-against-smoke.csv").read_text().splitlines()
    assert paired[1].startswith("row,column,kind,metric,difference") and len(paired) == 2 + 2 * 5 * 2
    assert (fresh / "table1-smoke-visible-against-smoke.md").is_file()
    assert main(smoke + against + ["--against", "quick"]) == 2
    assert "presets 'smoke' and 'quick' differ in frames" in capsys.readouterr().err
    # `--row`: a partial table of the rows named, from the same evaluations, beside the whole one
    whole = (shipped / "table1-smoke.md").read_text()
    from_zoo = ["--runs", str(shipped), "--out", str(shipped), "--trained", str(zoo)]
    evaluations = sorted((shipped / "eval").iterdir())
    assert main(smoke + from_zoo + ["--row", "LSTM A3C"]) == 0
    assert "training lstm_a3c" not in capsys.readouterr().out
    assert sorted((shipped / "eval").iterdir()) == evaluations and not (shipped / "train").exists()
    partial = (shipped / "table1-smoke-partial.md").read_text()
    assert "Partial: without the preset's rows Random walk." in partial
    lstm = [line for line in _numbers(whole) if line.startswith("| LSTM A3C |")]
    assert lstm and [line for line in _numbers(partial) if line.startswith("| LSTM A3C |")] == lstm
    assert "| Random walk |" in whole and "| Random walk |" not in partial
    # figures --row: that row's figures from the zoo, in OUT/partial/, nothing trained or evaluated
    figs = tmp_path / "figs"
    figures = ["figures", "--spec", str(spec_path), "--preset", "smoke", "--row", "LSTM A3C"]
    assert main(figures + ["--out", str(figs), "--runs", str(shipped), "--trained", str(zoo)]) == 0
    out = capsys.readouterr().out
    assert "training lstm_a3c" not in out and f"{figs / 'partial' / 'training_curves.png'}" in out, out
    assert sorted((shipped / "eval").iterdir()) == evaluations and [p.name for p in figs.iterdir()] == [
        "partial"
    ]
    for name in ("table1-smoke-partial.md", "table1-smoke-partial.tex", "table1-smoke-partial-ablation.csv"):
        assert "No comparison of the spec has both its rows in this table." in (shipped / name).read_text()
    assert (shipped / "table1-smoke.md").read_text() == whole  # never overwritten by a partial one
    for bad, named in (
        (["--row", "+KG"], "preset 'smoke' has no row '+KG'; its rows: Random walk; LSTM A3C"),
        (["--row", "LSTM A3C", "--job", "1"], "--row picks the rows of a table to assemble"),
        (["--row", "LSTM A3C", "--jobs"], "--jobs, --job and --train-only assemble none"),
        (["--row", "LSTM A3C", "--train-only"], "--row picks the rows of a table to assemble"),
    ):
        assert main(smoke + from_zoo + bad) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and named in err, err

    # the same job trained twice (again by newer code, the old run left beside it): the one this
    # checkout's code trained is used; two of older code are named, neither picked by folder name
    twin = zoo / (run.name[:-10] + "f" * 10)
    shutil.copytree(run, twin)
    config = json.loads((twin / "config.json").read_text())
    config["git_revision"] = "fedcba9876543210"
    (twin / "config.json").write_text(json.dumps(config))
    assert same_job_runs(zoo, twin) == [run] and same_job_runs(zoo, run) == [twin]  # as `ship` names it
    assert main(smoke + from_zoo + ["--row", "LSTM A3C"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "2 runs in" in err and "remove the superseded" in err, err
    assert "revision fedcba987654" in err and "revision 0123456789ab" in err
    ours = json.loads(next((trained / "train").glob("*/config.json")).read_text())["training_code_sha256"]
    config["training_code_sha256"] = ours
    (twin / "config.json").write_text(json.dumps(config))
    assert main(smoke + from_zoo + ["--row", "LSTM A3C"]) == 0
    assert "used as shipped" not in capsys.readouterr().out  # the twin, trained by this checkout's code
    shutil.rmtree(twin)

    # a zoo run whose config.json does not read (cut mid-way, not JSON, not a table): the error names
    # that file, not the closest other run
    original = (run / "config.json").read_text()
    for damaged in (original[: len(original) // 2], "{not json", "[]"):
        (run / "config.json").write_text(damaged)
        assert main(smoke + from_zoo + ["--row", "LSTM A3C"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"{run / 'config.json'} is unreadable" in err, err
        assert "the closest" not in err
    (run / "config.json").write_text(original)
    # the final weights of a run shipped without them: said so, naming no option `table` lacks
    smoke_last = [*smoke[:4], "smoke-last", *smoke[5:]]
    assert main(smoke_last + from_zoo + ["--row", "LSTM A3C"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "finished and has no last.pt: it was shipped without it" in err, err
    assert "--run" not in err and "ship RUN_DIR --last" in err

    # a run missing from the zoo, or trained with other options: one line, nothing trained
    missing = run
    config = json.loads((missing / "config.json").read_text())
    config["options"]["lr"] = 0.5
    (missing / "config.json").write_text(json.dumps(config))
    elsewhere = tmp_path / "elsewhere"
    assert main(smoke + ["--runs", str(elsewhere), "--trained", str(zoo)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"run in {zoo}" in err and "differs in options.lr" in err, err
    assert not (elsewhere / "train").exists()
    assert main(smoke + ["--trained", str(tmp_path / "nowhere"), "--runs", str(elsewhere)]) == 2
    assert "no such folder" in capsys.readouterr().err


def test_ship_refuses_what_it_cannot_ship_whole_and_never_replaces(tmp_path, capsys):
    """`ship` takes a finished run with checksummed checkpoints only; each refusal is one line, and
    leaves the zoo as it was: no half-shipped folder, an existing one untouched."""
    run = tmp_path / "runs" / "train" / "lstm_a3c-0123456789"
    run.mkdir(parents=True)
    zoo = tmp_path / "zoo"

    def ship(*extra) -> str:
        assert main(["ship", str(run), "--zoo", str(zoo), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("kgnavbench: error: "), err
        assert not list(zoo.iterdir())  # nothing shipped, no temporary folder left
        return err

    assert "not a training run" in ship()
    (run / "config.json").write_text("{not json")
    (run / "finished.json").write_text(json.dumps({"frames": 10}))
    assert "config.json is unreadable" in ship()
    (run / "config.json").write_text(json.dumps({"method": "lstm_a3c"}))
    assert "config.json is not a run's config.json: no seed" in ship()
    identity = {
        "method": "lstm_a3c",
        "seed": 0,
        "frames": 10,
        "options": {"il": False},
        "kitchens": ["FloorPlan1"],
    }
    (run / "config.json").write_text(json.dumps(identity))
    (run / "finished.json").unlink()
    assert "is not finished" in ship()
    (run / "finished.json").write_text("[]")
    assert "no frames" in ship()
    (run / "finished.json").write_text(json.dumps({"frames": 10}))
    assert "has no metrics.csv" in ship()
    (run / "metrics.csv").write_text("frames\n10\n")
    assert "best.pt does not exist" in ship()
    state = {"format": runs.CHECKPOINT_FORMAT, "updates": 0, "model": {}, "model_config": {}, "covis": {}}
    state.update({k: v for k, v in identity.items() if k != "frames"}, frames=10)
    # a checkpoint that is another run's (+IL's weights relabelled LSTM A3C, or absurd frames)
    runs.save_checkpoint(run / "best.pt", {**state, "options": {"il": True}})
    assert "is not the run its config.json describes: it differs in option il True" in ship()
    runs.save_checkpoint(run / "best.pt", {**state, "frames": 10**30})
    assert "differs in frames 1000000000000000000000000000000" in ship()
    runs.save_checkpoint(run / "best.pt", state)
    (run / "best.pt").write_bytes((run / "best.pt").read_bytes()[:-9] + b"corrupted")
    assert "does not match its checksum" in ship()
    runs.save_checkpoint(run / "best.pt", state)
    (run / "best.pt.sha256").unlink()
    assert "has no checksum" in ship()
    runs.save_checkpoint(run / "best.pt", {**state, "optimizer": {}})
    assert "last.pt does not exist" in ship("--last")
    runs.save_checkpoint(run / "last.pt", {**state, "frames": 20, "agents": {}})
    from kgnavbench.jobs import ZOO_LISTING_END, ZOO_LISTING_START

    readme = f"# my zoo\n\n{ZOO_LISTING_START}\n| stale |\n{ZOO_LISTING_END}\n\nnotes kept\n"
    (zoo / "README.md").write_text(readme)
    assert main(["ship", str(run), "--zoo", str(zoo), "--last"]) == 0
    assert f"rewrote the listing in {zoo / 'README.md'}" in capsys.readouterr().out
    listing = (zoo / "README.md").read_text()  # generated from the folder: its row (none), frames, last.pt
    assert listing.startswith(f"# my zoo\n\n{ZOO_LISTING_START}\n| run | row |") and "stale" not in listing
    assert listing.endswith(f"{ZOO_LISTING_END}\n\nnotes kept\n")
    assert (
        f"| `{run.name}` | none (closest: LSTM A3C; differs in " in listing
        and "| 0 | 10 | 10 | yes |" in listing
    )
    (zoo / "README.md").unlink()
    shipped = zoo / run.name
    assert (shipped.stat().st_mode & 0o777) == 0o755  # readable by everyone, as the files are
    for name, frames in (("best", 10), ("last", 20)):
        ck = runs.load_checkpoint(shipped / f"{name}.pt")  # its checksum verified
        assert ck == {**state, "frames": frames}  # weights only: no optimiser, no agents
    assert [p.name for p in zoo.iterdir()] == [run.name]  # no staging folder left
    before = {p.name: p.read_bytes() for p in (zoo / run.name).iterdir()}
    assert main(["ship", str(run), "--zoo", str(zoo)]) == 2
    assert "never replaced" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in (zoo / run.name).iterdir()} == before


def test_a_preset_scored_under_the_visible_rule_reuses_the_evaluations_and_says_so(
    tmp_path, capsys, monkeypatch
):
    """`score_rule = "visible"`: the same evaluations as the preset it copies (none of its own), each
    job's episodes scored under the visible rule (`evaluate.scored_visible`, tested against the visible
    rule's own evaluation in test_evaluate.py), and the caption says which rule and why."""
    from kgnavbench import jobs

    text = SPEC_FILE.read_text()
    head, tail = text.split("[presets.smoke]\n", 1)
    smoke_block = tail.split("\n\n", 1)[0]
    visible_block = (
        f'[presets.smoke-visible]\nscore_rule = "visible"\nrows = ["Random walk"]\n{smoke_block}\n\n'
    )
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(f'{head}{visible_block}[presets.smoke]\nrows = ["Random walk"]\n{tail}')
    runs_dir = tmp_path / "runs"
    scored = []
    monkeypatch.setattr(jobs, "scored_visible", lambda results: scored.append(results) or results)
    for preset in ("smoke", "smoke-visible"):
        argv = ["table", "--spec", str(spec_path), "--preset", preset, "--workers", "1"]
        assert main(argv + ["--runs", str(runs_dir), "--out", str(tmp_path)]) == 0
        assert len(scored) == (preset == "smoke-visible")  # smoke's own rule: nothing scored
    capsys.readouterr()
    (evaluation,) = (runs_dir / "eval").iterdir()  # one evaluation: both tables read it
    assert len(scored[0]) > 0 and all(r.stopped is not None for r in scored[0])
    caption = (tmp_path / "table1-smoke-visible.md").read_text()
    assert (
        "Stop with the target visible (SAVN's rule; the evaluations run under Stop at the destination"
        in caption
    )
    assert "success = Stop at the destination, " in (tmp_path / "table1-smoke.md").read_text()


def test_a_preset_with_checkpoint_last_evaluates_each_runs_final_weights(tmp_path, capsys):
    """A preset's `checkpoint = "last"` evaluates last.pt, not best.pt, and its caption says so; from
    a zoo that lacks last.pt it stops with one line naming the file."""
    text = SPEC_FILE.read_text()
    head, tail = text.split("[presets.smoke]\n", 1)
    smoke_block = tail.split("\n\n", 1)[0]
    last_block = f'[presets.smoke-last]\ncheckpoint = "last"\nrows = ["LSTM A3C"]\n{smoke_block}\n\n'
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(f'{head}{last_block}[presets.smoke]\nrows = ["LSTM A3C"]\n{tail}')
    runs_dir = tmp_path / "runs"
    for preset in ("smoke", "smoke-last"):
        argv = ["table", "--spec", str(spec_path), "--preset", preset, "--workers", "1"]
        assert main(argv + ["--runs", str(runs_dir), "--out", str(tmp_path)]) == 0
    (run,) = (runs_dir / "train").iterdir()  # one run: both presets train the same
    for preset in ("smoke", "smoke-last"):
        caption = (tmp_path / f"table1-{preset}.md").read_text()
        assert ("final weights (last.pt)" in caption) == (preset == "smoke-last")
    # the weights each evaluation froze: best.pt's and last.pt's (one evaluation where they are equal)
    tested = {(d / "weights.pt").read_bytes() for d in (runs_dir / "eval").iterdir()}
    assert tested == {(run / "best.pt").read_bytes(), (run / "last.pt").read_bytes()}
    capsys.readouterr()

    zoo = tmp_path / "zoo"
    assert main(["ship", str(run), "--zoo", str(zoo)]) == 0  # best.pt only
    argv = ["table", "--spec", str(spec_path), "--preset", "smoke-last", "--trained", str(zoo)]
    assert main(argv + ["--runs", str(tmp_path / "other"), "--out", str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "last.pt" in err, err


def test_train_with_a_preset_trains_the_run_the_table_would(tmp_path, capsys):
    """`train --preset P` is Table I's protocol for one row: the preset's options, frames and kitchens,
    so `table --preset P` finds that run finished; --set wins over the preset; a bad preset is one line."""
    text = SPEC_FILE.read_text()
    head, tail = text.split("[presets.smoke]\n", 1)
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(f'{head}[presets.smoke]\nrows = ["LSTM A3C"]\n{tail}')
    runs_dir = tmp_path / "runs"
    train = [
        "train",
        "--method",
        "lstm_a3c",
        "--spec",
        str(spec_path),
        "--preset",
        "smoke",
        "--runs",
        str(runs_dir),
    ]
    assert main(train) == 0
    directory = Path(capsys.readouterr().out.strip().splitlines()[-1])
    config = json.loads((directory / "config.json").read_text())
    smoke = load_spec(spec_path).presets["smoke"]
    assert config["frames"] == smoke.frames and config["kitchens"] == list(smoke.train_kitchens)
    assert config["options"]["lstm"] == 32 and config["options"]["agents_per_kitchen"] == 7
    assert (
        main(
            ["table", "--spec", str(spec_path), "--preset", "smoke", "--runs", str(runs_dir), "--train-only"]
            + ["--workers", "1"]
        )
        == 0
    )
    assert f"{directory} is a finished run" in capsys.readouterr().out
    assert main(train + ["--set", "lstm=16", "--frames", "500"]) == 0
    config = json.loads((Path(capsys.readouterr().out.strip().splitlines()[-1]) / "config.json").read_text())
    assert config["options"]["lstm"] == 16 and config["frames"] == 500
    assert main(["train", "--method", "lstm_a3c", "--preset", "nope", "--runs", str(runs_dir)]) == 2
    assert "unknown preset 'nope'" in capsys.readouterr().err


def test_jobs_prints_one_command_per_job_and_job_checks_its_number(capsys, tmp_path):
    assert main(["table", "--preset", "quick", "--runs", str(tmp_path), "--jobs"]) == 0
    lines = capsys.readouterr().out.splitlines()
    spec = load_spec()
    assert len(lines) == len(table_jobs(spec, spec.presets["quick"])) == 9 * 3
    assert lines[0].startswith("kgnavbench table --preset quick ") and lines[0].endswith(
        "--job 1  # Random walk (seed 0)"
    )
    assert lines[-1].endswith("--job 27  # +KG+Attention (seed 2)")
    # where the runs come from and where evaluations are kept carry over to every command
    sources = ["--trained", str(tmp_path / "zoo"), "--archive", str(tmp_path / "kept")]
    (tmp_path / "zoo").mkdir(), (tmp_path / "kept").mkdir()
    assert main(["table", "--preset", "quick", "--runs", str(tmp_path), "--jobs"] + sources) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 27 and all(
        f" --trained {tmp_path / 'zoo'} --archive {tmp_path / 'kept'} --job " in x for x in lines
    )
    (tmp_path / "zoo").rmdir(), (tmp_path / "kept").rmdir()
    assert main(["table", "--preset", "quick", "--runs", str(tmp_path), "--job", "28"]) == 2
    assert "jobs 1..27, not 28" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


def test_table_errors_are_one_line(capsys, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(GOOD.replace('method = "ff_a3c"', 'method = "ff_a4c"'))
    assert main(["table", "--spec", str(bad), "--runs", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "rows[3].method" in err and err.count("\n") == 1
    assert main(["table", "--preset", "huge", "--runs", str(tmp_path)]) == 2
    assert "unknown preset 'huge'" in capsys.readouterr().err


def test_names_in_printed_tables_and_commands_are_escaped(tmp_path, capsys):
    """What the table prints for others to read or run is safe: a row name with '|', a newline or
    TeX's specials stays one markdown cell and one LaTeX cell; `--jobs` quotes every argument for the
    shell and keeps a row's name in its one-line comment; a preset name cannot leave --out."""
    result = fake_result()
    odd = "+KG | {x}$_%^~ \\ & #\nnext"
    result.rows[1] = dataclasses.replace(
        result.rows[1], row=dataclasses.replace(result.rows[1].row, name=odd)
    )
    md = to_markdown(result)
    line = next(line for line in md.splitlines() if line.startswith("| +KG \\| "))
    assert len(_cells_of(line.replace("\\|", "/"))) == len(_cells_of(md.splitlines()[2]))
    tex = to_latex(result)
    assert r"+KG | \{x\}\$\_\%\textasciicircum{}\textasciitilde{} \textbackslash{} \& \# next" in tex
    # --jobs: a runs folder with a space and a spec path with a quote come back as one argument each
    spec_path = tmp_path / "it's a spec.toml"
    spec_path.write_text(GOOD)
    runs_dir = tmp_path / "my runs; touch X"
    assert (
        main(["table", "--spec", str(spec_path), "--preset", "smoke", "--runs", str(runs_dir), "--jobs"]) == 0
    )

    for line in capsys.readouterr().out.splitlines():
        printed, _, comment = line.partition("  # ")
        words = shlex.split(printed)
        assert words[words.index("--runs") + 1] == str(runs_dir)
        assert words[words.index("--spec") + 1] == str(spec_path)
        assert "\n" not in comment
    assert not (tmp_path / "X").exists() and not runs_dir.exists()
    # a preset name that would leave the folder is refused where the spec is read
    bad = GOOD.replace("[presets.smoke]", '[presets."sub/../../escaped"]', 1)
    with pytest.raises(TableError, match="preset name 'sub/../../escaped' must be letters"):
        parse_spec(bad, "tables/bad.toml")


def test_a_row_without_unseen_kitchens_gets_no_cells_where_every_kitchen_is_unseen(tmp_path):
    """FF A3C has no row for unseen kitchens: in a preset whose evaluation kitchens are all unseen it
    is evaluated nowhere (no kitchens used to mean the whole split) and its cells stay empty."""
    from kgnavbench.jobs import Job, eval_kitchens, run_row

    spec = load_spec()
    rows = {r.name: r for r in spec.rows}
    preset = dataclasses.replace(spec.presets["smoke"], eval_kitchens=("FloorPlan27",))
    assert eval_kitchens(preset, rows["FF A3C"]) == ()
    row = dataclasses.replace(rows["FF A3C"], method="random_walk", options={})  # nothing to train
    _, run = run_row(
        Job(spec=spec, preset=preset, row=row, seed=0, runs_dir=tmp_path), progress=lambda line: None
    )
    assert run.results == [] and not (tmp_path / "eval").exists()


KILLER = '''"""A plugin whose worker dies: SIGKILL in make_policy, as the OOM killer would."""
import os
import signal

DESCRIPTION = "dies"


def make_policy(config, spec):
    os.kill(os.getpid(), signal.SIGKILL)
'''

TWO_ROWS = """
[protocol]
success_rule = "destination"
stop_ends = true
seen_cap = 100
unseen_cap = 1000
checkpoint = "best_val_sr"

[presets.tiny]
frames = 1000
episodes = 1
seeds = 1
train_kitchens = ["FloorPlan1"]
eval_kitchens = ["FloorPlan1"]

[[rows]]
name = "Random walk"
method = "random_walk"

[[rows]]
name = "Killed"
method = "killer"
"""


def test_a_lost_worker_loses_its_job_only_named_and_a_rerun_resumes(tmp_path, hermetic_cache):
    """With --workers 2, a job whose worker process is killed (a signal, the OOM killer) is named in
    one line, exit 2; the other job finishes and is kept, so a rerun only reruns the lost one."""
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "killer.py").write_text(KILLER)
    (tmp_path / "spec.toml").write_text(TWO_ROWS)
    env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache)}
    command = [sys.executable, "-m", "kgnavbench", "table", "--spec", "spec.toml", "--preset", "tiny"]
    command += ["--runs", "runs", "--out", "out", "--workers", "2"]
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and done.stderr.count("\n") == 1
    assert "1 of 2 jobs lost their worker process ([2/2] Killed (seed 0))" in done.stderr
    assert "== done [1/2] Random walk (seed 0)" in done.stdout
    assert list((tmp_path / "runs" / "eval").glob("random_walk-*/episodes/FloorPlan1.jsonl"))


def test_a_worker_that_died_between_jobs_costs_no_job(tmp_path, monkeypatch):
    """A worker's process takes the next job; one that died after its last job (its pool broken while
    idle) is replaced when the next job is submitted, so no job is lost and no job runs twice. Faked in
    this process: pools that run a job at once, the first of which breaks after its first job."""
    import concurrent.futures

    from kgnavbench import jobs

    made = []

    class Pool:  # a ProcessPoolExecutor of one worker, as run_jobs uses it
        def __init__(self, *args, **kwargs):
            self.broken, self.ran, self.shut = False, [], False
            made.append(self)

        def submit(self, fn, job, progress):
            if self.broken:
                raise concurrent.futures.process.BrokenProcessPool("its worker died")
            future = concurrent.futures.Future()
            future.set_result(fn(job, progress))
            self.ran.append(job.seed)
            self.broken = self is made[0]  # the first pool's worker dies once its first job is done
            return future

        def shutdown(self, wait=True, cancel_futures=False):
            self.shut = True

    monkeypatch.setattr(concurrent.futures, "ProcessPoolExecutor", Pool)
    monkeypatch.setattr(
        jobs, "execute", lambda job, progress: jobs.JobOutcome({}, "", str(job.seed), 1.0, False)
    )
    spec = load_spec()
    walk = next(row for row in spec.rows if row.method == "random_walk")
    table = [
        jobs.Job(spec=spec, preset=spec.preset("smoke"), row=walk, seed=seed, runs_dir=tmp_path)
        for seed in range(5)
    ]
    outcomes = jobs.run_jobs(table, progress=lambda line: None, workers=2)
    assert [o.eval_run for o in outcomes] == ["0", "1", "2", "3", "4"]
    assert sorted(seed for pool in made for seed in pool.ran) == [0, 1, 2, 3, 4]
    assert len(made[0].ran) == 1 and len(made) == 3  # the broken one dropped, one fresh pool in its place
    assert all(pool.shut for pool in made)  # none left running


def test_ship_refuses_links_odd_names_and_odd_frames_and_clears_its_leftovers(tmp_path, capsys):
    """What `ship` reads back is checked: no symbolic link is followed into the zoo, a folder or method
    name that is not printable ASCII of a run's shape is refused (shown escaped), finished.json's frames
    must be a whole number, and a staging folder a killed ship left is removed by the next ship."""
    zoo = tmp_path / "zoo"

    def make_run(name: str, method: str = "lstm_a3c", frames=10) -> Path:
        run = tmp_path / "runs" / name
        run.mkdir(parents=True)
        identity = {"method": method, "seed": 0, "frames": 10, "options": {}, "kitchens": ["FloorPlan1"]}
        (run / "config.json").write_text(json.dumps(identity))
        (run / "finished.json").write_text(json.dumps({"frames": frames}))
        (run / "metrics.csv").write_text("frames\n10\n")
        state = {"format": runs.CHECKPOINT_FORMAT, "updates": 0, "model": {}, "model_config": {}, "covis": {}}
        state.update({k: v for k, v in identity.items()})
        runs.save_checkpoint(run / "best.pt", state)
        return run

    def refused(run: Path) -> str:
        assert main(["ship", str(run), "--zoo", str(zoo)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and ("not shipped" in err or "symbolic link" in err), err
        assert not zoo.exists() or not [p for p in zoo.iterdir() if not p.name.startswith(".")]
        return err

    linked = make_run("lstm_a3c-00000000aa")
    (linked / "metrics.csv").unlink()
    (linked / "metrics.csv").symlink_to("/etc/hostname")
    assert "metrics.csv is a symbolic link" in refused(linked)
    cyrillic = make_run("lstm_a3\u0441-00000000bb")  # a Cyrillic "с"
    assert "'lstm_a3\\u0441-00000000bb' is not a run folder's name" in refused(cyrillic)
    assert "is not a run folder's name" in refused(make_run(".lstm_a3c-00000000cc"))
    assert "is not a run folder's name" in refused(make_run("lstm_a3c\u202e-00000000dd"))
    assert "names the method 'lstm_a3\\u0441'" in refused(
        make_run("lstm_a3c-00000000ee", method="lstm_a3\u0441")
    )
    for i, frames in enumerate(["10", 1e309, 2.5, -1, True]):
        run = make_run(f"lstm_a3c-0000000{i}f0")
        (run / "finished.json").write_text(json.dumps({"frames": frames}).replace("1e309", "Infinity"))
        assert "is not a whole number" in refused(run)
    # a killed ship's staging folder is cleared by the next ship of that run, which then ships whole
    good = make_run("lstm_a3c-0123456789")
    zoo.mkdir(exist_ok=True)
    (zoo / f".{good.name}-killed.tmp").mkdir()
    assert main(["ship", str(good), "--zoo", str(zoo)]) == 0
    assert [p.name for p in zoo.iterdir()] == [good.name]


def test_training_is_announced_with_its_cost_before_it_starts(tmp_path):
    """Before a table trains, one line says how many runs will train and about how many core-hours;
    finished runs are not counted, and nothing is said when nothing trains."""
    from kgnavbench import jobs as table_module
    from kgnavbench.plugins import load_plugin

    spec = load_spec()
    preset = spec.preset("paper")
    jobs = [(row, seed) for row, seed in table_jobs(spec, preset) if row.name in ("+KG", "+KG+Attention")]
    lines = []
    table_module.announce_training(preset, jobs, tmp_path, "cpu", lines.append)
    n = len(jobs)  # +KG's seeds (the spec's row_seeds) and +KG+Attention's 3
    assert n == preset.seeds_of("+KG") + preset.seeds_of("+KG+Attention")
    hours = n * 40_000_000 / table_module.FRAMES_PER_CORE_SECOND / 3600
    assert lines == [
        f"== training {n} of the preset's {n} runs (40,000,000 frames each; finished ones are reused, "
        f"unfinished ones resume): about {hours:.1f} core-hours on a CPU"
    ]
    row, seed = jobs[0]
    plugin = load_plugin(row.method)
    record = runs.run_record(
        plugin,
        plugin.config({**preset.options, **row.options}),
        preset.frames,
        seed,
        runs.training_kitchens(preset.train_kitchens),
        "cpu",
    )
    finished = runs.run_directory(tmp_path, record)
    finished.mkdir(parents=True)
    (finished / "finished.json").write_text("{}")
    lines.clear()
    table_module.announce_training(preset, jobs, tmp_path, "cpu", lines.append)
    assert lines[0].startswith(f"== training {n - 1} of the preset's {n} runs")
    lines.clear()
    table_module.announce_training(preset, jobs[:1], tmp_path, "cpu", lines.append)
    assert lines == []


def test_verdicts_only_recomputes_a_written_tables_verdicts_as_the_writer_would(tmp_path, capsys):
    """`table --verdicts-only`: the verdicts of written tables recomputed from their ablation CSV under
    the spec's margin equal what the writer gives from the episodes under that margin; the main table
    is kept; a damaged CSV or another option is one line, and nothing is rewritten."""
    wide = tmp_path / "wide.toml"
    wide.write_text(SPEC_FILE.read_text().replace("\nmargin = 3\n", "\nmargin = 0\n"))
    old = fake_result()
    old.spec = load_spec(wide)
    written = tmp_path / "written"
    written.mkdir()
    write_table(old, written)
    ablation = (written / "table1-ablation.csv").read_text()
    assert "margin of 0 points" in ablation and ",no difference beyond 0\n" in ablation
    expected = tmp_path / "expected"
    expected.mkdir()
    write_table(fake_result(), expected)  # the committed spec: margin 3
    assert main(["table", "--verdicts-only", "--out", str(written)]) == 0
    for name in ("table1-ablation.csv", "table1.md", "table1.tex", "table1.csv"):
        # (the captions hold the wall time and revision of the table that was written: the same here)
        assert (written / name).read_text() == (expected / name).read_text(), name
    assert ",no difference beyond 3\n" in (written / "table1-ablation.csv").read_text()
    assert "wrote " in capsys.readouterr().out
    # another option, or a damaged CSV: one line, exit 2, nothing rewritten
    before = {p.name: p.read_bytes() for p in written.iterdir()}
    assert main(["table", "--verdicts-only", "--out", str(written), "--row", "IL"]) == 2
    assert (
        "--verdicts-only rewrites written tables and runs nothing: not with --row" in capsys.readouterr().err
    )
    (written / "table1-ablation.csv").write_text(ablation.replace(",75,", ",seventy,", 1))
    assert main(["table", "--verdicts-only", "--out", str(written)]) == 2
    err = capsys.readouterr().err
    assert "table1-ablation.csv, line" in err and err.count("\n") == 1
    assert main(["table", "--verdicts-only", "--preset", "smoke", "--out", str(written)]) == 2
    assert "table1-smoke-ablation.csv" in capsys.readouterr().err
    assert (written / "table1.md").read_bytes() == before["table1.md"]
