"""The evaluation protocol (evaluate stage): SPL and the other metrics on hand-computed episodes,
columns and caps, the oracle's 100/100, determinism and resuming a run."""

import dataclasses
import json
import math
from pathlib import Path

import pytest

from kgnavbench.evaluate import (
    EvalConfig,
    EvalError,
    column_of,
    episode_cap,
    evaluate,
    kitchens_of_split,
)
from kgnavbench.metrics import EpisodeResult, format_summary, metrics, spl_term, summarize
from kgnavbench.tasks import load_task_file


def episode(success, path, shortest, column="seen_seen", kind="static", collisions=0, last=None, length=None):
    return EpisodeResult(
        kitchen="FloorPlan1",
        target="Apple|x",
        kind=kind,
        column=column,
        start=0,
        max_steps=100,
        success=success,
        path_length=path,
        shortest_path=shortest,
        collisions=collisions,
        last_view_shows_target=success if last is None else last,
        episode_length=path + 1 if length is None else length,
    )


def test_spl_on_hand_computed_episodes():
    # success on the shortest path: 1; success with a detour: L / P; failure: 0
    assert spl_term(episode(True, 10, 10)) == 1.0
    assert spl_term(episode(True, 20, 10)) == 0.5
    assert spl_term(episode(True, 12, 3)) == 0.25
    assert spl_term(episode(False, 10, 10)) == 0.0
    m = metrics([episode(True, 10, 10), episode(True, 20, 10), episode(False, 7, 4), episode(True, 12, 3)])
    assert m.episodes == 4
    assert m.sr == pytest.approx(75.0)
    assert m.spl == pytest.approx(100 * (1 + 0.5 + 0 + 0.25) / 4)
    # the L>=5 bucket leaves out the episodes whose shortest path is 3 and 4
    assert m.episodes_long == 2
    assert m.sr_long == pytest.approx(100.0)
    assert m.spl_long == pytest.approx(75.0)


def test_collisions_last_view_and_length_are_means_per_episode():
    m = metrics(
        [
            episode(False, 100, 12, collisions=7, last=True, length=100),
            episode(True, 15, 12, collisions=1, length=16),
            episode(False, 3, 12, collisions=0, last=False, length=4),
        ]
    )
    assert m.collisions == pytest.approx(8 / 3)
    assert m.last_view_shows_target == pytest.approx(200 / 3)
    assert m.episode_length == pytest.approx(120 / 3)
    assert m.sr == pytest.approx(100 / 3)


def test_an_empty_bucket_is_nan_not_zero():
    m = metrics([episode(True, 3, 3)])
    assert m.episodes_long == 0 and math.isnan(m.sr_long) and math.isnan(m.spl_long)


def test_summary_groups_by_column_and_kind():
    results = [
        episode(True, 10, 10, "seen_seen", "static"),
        episode(False, 10, 10, "seen_seen", "actionable"),
        episode(True, 20, 10, "unseen_kitchens", "static"),
    ]
    s = summarize(results)
    assert list(s) == [
        ("seen_seen", "static"),
        ("seen_seen", "actionable"),
        ("seen_seen", "all"),
        ("unseen_kitchens", "static"),
        ("unseen_kitchens", "actionable"),  # no episodes: an empty cell, shown as "–"
        ("unseen_kitchens", "all"),
        ("all", "all"),
    ]
    assert s[("seen_seen", "static")].sr == 100 and s[("seen_seen", "actionable")].sr == 0
    assert s[("seen_seen", "all")].sr == 50 and s[("unseen_kitchens", "all")].spl == 50
    assert s[("unseen_kitchens", "actionable")].episodes == 0
    table = format_summary(s, "title")
    assert table.splitlines()[0] == "title"
    assert "seen kitchens / seen targets" in table and "unseen kitchens" in table
    empty = [line for line in table.splitlines() if "unseen kitchens" in line and "actionable" in line]
    assert len(empty) == 1 and empty[0].count(" – |") == 7 and " 0.00 " not in empty[0]


def test_columns_and_caps_follow_the_design():
    assert column_of("train", True) == "seen_seen" and episode_cap("seen_seen") == 100
    assert column_of("train", False) == "seen_unseen" and episode_cap("seen_unseen") == 1000
    assert column_of("test", True) == column_of("test", False) == "unseen_kitchens"
    assert episode_cap("unseen_kitchens") == 1000
    assert column_of("val", True) == "validation"
    splits = load_task_file()["splits"]
    assert kitchens_of_split("table") == sorted(
        splits["train"] + splits["test"], key=lambda k: int(k.removeprefix("FloorPlan"))
    )


def test_bad_configs_are_rejected():
    with pytest.raises(EvalError, match="success rule"):
        EvalConfig("oracle", success_rule="anywhere")
    with pytest.raises(EvalError, match="split"):
        EvalConfig("oracle", split="dev")
    with pytest.raises(EvalError, match="episodes per target"):
        EvalConfig("oracle", episodes_per_target=101)
    with pytest.raises(ValueError, match="FloorPlan99"):
        EvalConfig("oracle", kitchens=("FloorPlan99",))
    with pytest.raises(ValueError, match="unknown kitchen 'FloorPlan99'"):
        EvalConfig("oracle", unseen_target_kitchens=("FloorPlan99",))
    with pytest.raises(EvalError, match="FloorPlan27 is not a training kitchen of this evaluation"):
        EvalConfig("oracle", unseen_target_kitchens=("FloorPlan27",))  # a test kitchen
    with pytest.raises(EvalError, match="FloorPlan2 is not a training kitchen of this evaluation"):
        EvalConfig("oracle", kitchens=("FloorPlan1",), unseen_target_kitchens=("FloorPlan2",))
    with pytest.raises(EvalError, match="named twice"):
        EvalConfig("oracle", unseen_target_kitchens=("FloorPlan1", "FloorPlan1"))


def test_unseen_targets_in_some_kitchens_only(tmp_path, floorplan1_tasks):
    """A training kitchen left out of unseen_target_kitchens runs its seen targets only, resumes from
    its results file, and an evaluation without the field keeps the name it always had."""
    every = EvalConfig("oracle", kitchens=("FloorPlan1",), episodes_per_target=2)
    named = dataclasses.replace(every, unseen_target_kitchens=("FloorPlan1",))
    only_seen = dataclasses.replace(
        every, kitchens=("FloorPlan1", "FloorPlan2"), unseen_target_kitchens=("FloorPlan2",)
    )
    assert not named.seen_targets_only("FloorPlan1") and only_seen.seen_targets_only("FloorPlan1")
    quiet = lambda line: None  # noqa: E731
    full, same = evaluate(every, tmp_path, quiet), evaluate(named, tmp_path / "b", quiet)
    assert full.results == same.results and {r.column for r in full.results} == {"seen_seen", "seen_unseen"}
    identity = json.loads((full.directory / "config.json").read_text())["identity"]["config"]
    assert "unseen_target_kitchens" not in identity  # left out when empty: older evaluations keep names
    assert same.directory.name != full.directory.name
    run = evaluate(only_seen, tmp_path, quiet)
    seen = [r for r in full.results if r.column == "seen_seen"]
    assert [r for r in run.results if r.kitchen == "FloorPlan1"] == seen
    assert {r.column for r in run.results if r.kitchen == "FloorPlan2"} == {"seen_seen", "seen_unseen"}
    again = evaluate(only_seen, tmp_path, quiet)
    assert again.resumed == ["FloorPlan1", "FloorPlan2"] and again.results == run.results
    assert "unseen targets in FloorPlan2 only" in (run.directory / "table.md").read_text()
    # the same kitchens in another order are the same evaluation
    listed = dataclasses.replace(only_seen, unseen_target_kitchens=("FloorPlan2", "FloorPlan1"))
    assert listed.unseen_target_kitchens == ("FloorPlan1", "FloorPlan2")


@pytest.mark.parametrize("rule", ["visible", "destination"])
def test_the_oracle_scores_sr_100_and_spl_100(tmp_path, floorplan1_tasks, rule):
    config = EvalConfig("oracle", success_rule=rule, kitchens=("FloorPlan1",), episodes_per_target=3)
    run = evaluate(config, tmp_path, progress=lambda line: None)
    assert len(run.results) == 3 * len(floorplan1_tasks.targets)
    overall = run.summary[("all", "all")]
    assert overall.sr == 100.0 and overall.spl == pytest.approx(100.0)
    assert overall.collisions == 0 and overall.last_view_shows_target == 100.0
    kinds = {r.kind for r in run.results}
    assert kinds == {"static", "actionable"}
    for r in run.results:
        assert r.path_length == r.shortest_path and r.episode_length == r.path_length + 1


def test_destination_rule_paths_are_never_shorter(tmp_path, floorplan1_tasks):
    runs = {
        rule: evaluate(
            EvalConfig("oracle", success_rule=rule, kitchens=("FloorPlan1",), episodes_per_target=2),
            tmp_path,
            progress=lambda line: None,
        )
        for rule in ("visible", "destination")
    }
    for a, b in zip(runs["visible"].results, runs["destination"].results, strict=True):
        assert (a.target, a.start) == (b.target, b.start)
        assert b.shortest_path >= a.shortest_path
        assert b.shortest_path >= 10  # starts are at least 10 actions from the destination


def test_an_evaluation_scored_under_the_visible_rule_is_the_visible_rules_evaluation(
    tmp_path, floorplan1_tasks
):
    """With Stop ending the episode the two rules give the same episodes: the destination rule's
    evaluation scored by `scored_visible` equals the visible rule's own, episode by episode (success,
    SPL's shortest path, everything). Results written before `stopped` was recorded are refused."""
    from kgnavbench.evaluate import scored_visible

    def run(rule):
        config = EvalConfig(
            "random_walk",
            options=(("stop_probability", "0.01"),),  # some episodes end by their cap
            success_rule=rule,
            kitchens=("FloorPlan1",),
            episodes_per_target=3,
        )
        return evaluate(config, tmp_path, progress=lambda line: None).results

    destination, visible = run("destination"), run("visible")
    assert any(r.stopped for r in destination) and not all(r.stopped for r in destination)
    assert scored_visible(destination) == visible
    assert sum(r.success for r in visible) > sum(r.success for r in destination)  # the rules differ here
    with pytest.raises(EvalError, match="predate the record of whether an episode ended by Stop"):
        scored_visible([dataclasses.replace(destination[0], stopped=None)])


def test_random_walk_is_deterministic_and_resumes(tmp_path, floorplan1_tasks):
    config = EvalConfig(
        "random_walk",
        success_rule="visible",
        stop_ends=False,
        kitchens=("FloorPlan1",),
        episodes_per_target=2,
        seed=3,
    )
    lines = []
    first = evaluate(config, tmp_path / "a", progress=lines.append)
    again = evaluate(config, tmp_path / "b", progress=lambda line: None)
    assert first.results == again.results
    assert len(lines) == 2 and lines[0] == "evaluating random_walk: 1 kitchens, 68 episodes"
    assert "agent-steps/s" in lines[1]
    # the same config in the same runs dir resumes from the saved kitchen instead of rerunning it
    resumed = evaluate(config, tmp_path / "a", progress=lines.append)
    assert resumed.resumed == ["FloorPlan1"] and resumed.results == first.results and len(lines) == 2
    saved = json.loads((first.directory / "config.json").read_text())
    assert saved["identity"]["config"]["method"] == "random_walk" and saved["git_revision"]
    assert saved["machine"]["cpu"] and "machine" not in saved["identity"]  # recorded, decides nothing
    assert saved["identity"]["plugin_config"] == {"stop_probability": 0.1}
    assert first.directory.name.startswith("random_walk-visible-stop-noop-")
    # a wrong Stop is a no-op: failed episodes run to the cap
    for r in first.results:
        assert r.success or r.episode_length == r.max_steps


DAMAGE = {
    "not json": lambda text: "{not json\n",
    "truncated": lambda text: text[: len(text) // 2],
    "a line missing": lambda text: "".join(text.splitlines(keepends=True)[:-1]),
    "a line twice": lambda text: text + text.splitlines(keepends=True)[0],
    "a string for a bool": lambda text: text.replace('"success": true', '"success": "yes"', 1),
    "a float for an int": lambda text: text.replace('"collisions": 0', '"collisions": 0.0', 1),
    "another episode": lambda text: text.replace('"start": ', '"start": 1', 1),
}


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_damaged_results_file_is_set_aside_and_rerun_never_summed(
    tmp_path, floorplan1_tasks, damage, capsys
):
    config = EvalConfig("oracle", kitchens=("FloorPlan1",), episodes_per_target=1)
    run = evaluate(config, tmp_path, progress=lambda line: None)
    path = run.directory / "episodes" / "FloorPlan1.jsonl"
    good = path.read_text()
    bad = DAMAGE[damage](good)
    assert bad != good
    path.write_text(bad)
    again = evaluate(config, tmp_path, progress=lambda line: None)
    assert again.resumed == [] and again.results == run.results  # re-run, not summed
    assert path.read_text() == good
    aside = list(path.parent.glob("FloorPlan1.jsonl.corrupt-*"))
    assert len(aside) == 1 and aside[0].read_text() == bad  # the damaged file is kept, not lost
    assert "is damaged" in capsys.readouterr().err


def test_config_json_is_written_once(tmp_path, floorplan1_tasks):
    config = EvalConfig("oracle", kitchens=("FloorPlan1",), episodes_per_target=1)
    run = evaluate(config, tmp_path, progress=lambda line: None)
    path = run.directory / "config.json"
    text, mtime = path.read_text(), path.stat().st_mtime_ns
    evaluate(config, tmp_path, progress=lambda line: None)
    assert path.read_text() == text and path.stat().st_mtime_ns == mtime


def test_the_run_name_hashes_the_plugins_source_and_resolved_config(tmp_path, monkeypatch, floorplan1_tasks):
    from kgnavbench import plugins

    local = tmp_path / "baselines"
    local.mkdir()
    monkeypatch.chdir(tmp_path)
    source = (plugins.SOURCE_BASELINES_DIR / "random_walk.py").read_text()
    (local / "walker.py").write_text(source)
    config = EvalConfig("walker", kitchens=("FloorPlan1",), episodes_per_target=1)
    first = evaluate(config, tmp_path / "runs", progress=lambda line: None)
    # the same options, another default in the plugin: its resolved config and source differ
    (local / "walker.py").write_text(
        source.replace("stop_probability: float = 0.1", "stop_probability: float = 0.5")
    )
    second = evaluate(config, tmp_path / "runs", progress=lambda line: None)
    assert second.directory != first.directory and second.resumed == []
    # only a comment changed: the source differs, so does the run
    (local / "walker.py").write_text(source + "# a comment\n")
    third = evaluate(config, tmp_path / "runs", progress=lambda line: None)
    assert third.directory not in (first.directory, second.directory)
    # the identical plugin again: the first run resumes
    (local / "walker.py").write_text(source)
    assert evaluate(config, tmp_path / "runs", progress=lambda line: None).resumed == ["FloorPlan1"]


def test_another_config_in_the_same_run_directory_is_refused(tmp_path, floorplan1_tasks):
    config = EvalConfig("oracle", kitchens=("FloorPlan1",), episodes_per_target=1)
    run = evaluate(config, tmp_path, progress=lambda line: None)
    saved = json.loads((run.directory / "config.json").read_text())
    saved["identity"]["config"]["seed"] = 99
    (run.directory / "config.json").write_text(json.dumps(saved))
    with pytest.raises(EvalError, match="another config"):
        evaluate(config, tmp_path, progress=lambda line: None)
    saved["identity"]["config"]["seed"] = 0
    saved["identity"]["plugin_source_sha256"] = "0" * 64
    (run.directory / "config.json").write_text(json.dumps(saved))
    with pytest.raises(EvalError, match="differs in plugin_source_sha256"):
        evaluate(config, tmp_path, progress=lambda line: None)


def test_a_runs_folder_that_cannot_be_written_is_an_error_and_writes_nothing(tmp_path, floorplan1_tasks):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    config = EvalConfig("oracle", kitchens=("FloorPlan1",), episodes_per_target=1)
    with pytest.raises(EvalError, match="cannot write .*config.json"):
        evaluate(config, blocker / "runs", progress=lambda line: None)
    assert blocker.read_text() == "not a folder"


def test_a_results_file_without_its_checksum_is_rerun_never_trusted(tmp_path, floorplan1_tasks, capsys):
    """A results file whose sha256 was deleted proves nothing: even well formed (here: every episode
    edited into a success), it is set aside and the kitchen re-run, never resumed."""
    config = EvalConfig("random_walk", kitchens=("FloorPlan1",), episodes_per_target=1)
    run = evaluate(config, tmp_path, progress=lambda line: None)
    path = run.directory / "episodes" / "FloorPlan1.jsonl"
    good = path.read_text()
    edited = good.replace('"success": false', '"success": true')
    assert edited != good
    path.write_text(edited)
    (path.parent / "FloorPlan1.jsonl.sha256").unlink()
    again = evaluate(config, tmp_path, progress=lambda line: None)
    assert again.resumed == [] and again.results == run.results and path.read_text() == good
    assert "checksum FloorPlan1.jsonl.sha256 is missing" in capsys.readouterr().err


FILE_POLICY = """
from dataclasses import dataclass

DESCRIPTION = "acts the one action its weights file holds"


@dataclass
class Config:
    weights: str = ""


class Policy:
    def __init__(self, action):
        self.action = action

    def reset(self, agent):
        pass

    def act(self, observations, infos):
        return {agent: self.action for agent in observations}


def make_policy(config, spec):
    with open(config.weights) as f:
        return Policy(int(f.read()))
"""


def test_a_rewritten_weights_file_is_a_new_evaluation(tmp_path, monkeypatch, floorplan1_tasks):
    """An evaluation's identity covers the content of every file an option names: the same path
    rewritten gives new results, never the old ones resumed."""
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "filed.py").write_text(FILE_POLICY)
    monkeypatch.chdir(tmp_path)
    weights = tmp_path / "weights.txt"
    config = EvalConfig("filed", options=(("weights", str(weights)),), kitchens=("FloorPlan1",))
    config = dataclasses.replace(config, episodes_per_target=1)
    weights.write_text("9")  # Stop at once
    first = evaluate(config, tmp_path / "runs", progress=lambda line: None)
    weights.write_text("2")  # turn forever
    second = evaluate(config, tmp_path / "runs", progress=lambda line: None)
    assert second.directory != first.directory and second.resumed == []
    assert {r.episode_length for r in first.results} == {1}
    assert min(r.episode_length for r in second.results) > 1


def test_a_packed_evaluation_rebuilds_its_results_byte_for_byte_and_resumes(tmp_path, floorplan1_tasks):
    """`pack_evaluation` keeps a finished evaluation in one file (the same bytes each time);
    `unpack_evaluation` rebuilds it in another runs folder, where the same config resumes from it
    without running an episode; damage, a foreign archive or another evaluation's folder is refused."""
    from kgnavbench.archives import pack_evaluation, unpack_evaluation

    config = EvalConfig("random_walk", kitchens=("FloorPlan1",), episodes_per_target=2, seed=3)
    first = evaluate(config, tmp_path / "a", progress=lambda line: None)
    packed = pack_evaluation(first.directory, tmp_path / "packed")
    assert packed.name == f"{first.directory.name}.tar.xz"
    assert pack_evaluation(first.directory, tmp_path / "again").read_bytes() == packed.read_bytes()
    rebuilt = unpack_evaluation(packed, tmp_path / "b" / "eval")
    for name in ("config.json", "episodes/FloorPlan1.jsonl", "episodes/FloorPlan1.jsonl.sha256"):
        assert (rebuilt / name).read_bytes() == (first.directory / name).read_bytes()
    lines = []
    resumed = evaluate(config, tmp_path / "b", progress=lines.append)
    assert resumed.resumed == ["FloorPlan1"] and resumed.results == first.results and not lines
    assert unpack_evaluation(packed, tmp_path / "b" / "eval") == rebuilt  # what is there is kept
    # the same evaluation started by another checkout (its recorded revision differs), a kitchen
    # missing: its config.json stays, the kitchen is added
    saved = json.loads((rebuilt / "config.json").read_text())
    saved["git_revision"] = "another checkout"
    (rebuilt / "config.json").write_text(json.dumps(saved))
    for name in ("FloorPlan1.jsonl", "FloorPlan1.jsonl.sha256"):
        (rebuilt / "episodes" / name).unlink()
    assert unpack_evaluation(packed, tmp_path / "b" / "eval") == rebuilt
    assert json.loads((rebuilt / "config.json").read_text())["git_revision"] == "another checkout"
    assert (rebuilt / "episodes" / "FloorPlan1.jsonl").read_bytes() == (
        first.directory / "episodes" / "FloorPlan1.jsonl"
    ).read_bytes()
    # the same evaluation with other results in the runs folder, intact (another machine's floats):
    # refused, nothing unpacked and nothing changed
    episodes = rebuilt / "episodes" / "FloorPlan1.jsonl"
    archived = episodes.read_bytes()
    other_results = archived.replace(b'"path_length": ', b'"path_length": 1', 1)
    assert other_results != archived
    from kgnavbench.files import write_with_checksum

    write_with_checksum(episodes, other_results)
    before = {p: p.read_bytes() for p in rebuilt.rglob("*") if p.is_file()}
    with pytest.raises(EvalError, match="holds other episodes than .*nothing unpacked"):
        unpack_evaluation(packed, tmp_path / "b" / "eval")
    assert {p: p.read_bytes() for p in rebuilt.rglob("*") if p.is_file()} == before
    # damaged (its checksum does not prove it): set aside, as evaluate does, and the archive's written
    episodes.write_bytes(b"half a line")
    assert unpack_evaluation(packed, tmp_path / "b" / "eval") == rebuilt
    assert episodes.read_bytes() == archived and len(list(episodes.parent.glob("*.corrupt-*"))) == 1
    # another evaluation's folder of that name is refused, and left as it was
    other = tmp_path / "c" / "eval" / first.directory.name
    other.mkdir(parents=True)
    (other / "config.json").write_text("{}")
    with pytest.raises(EvalError, match="holds another evaluation"):
        unpack_evaluation(packed, tmp_path / "c" / "eval")
    assert (other / "config.json").read_text() == "{}" and not (other / "episodes").exists()
    damaged = tmp_path / "damaged" / packed.name
    damaged.parent.mkdir()
    data = bytearray(packed.read_bytes())
    data[len(data) // 2] ^= 0xFF
    damaged.write_bytes(bytes(data))
    with pytest.raises(EvalError, match="cannot be read as a packed evaluation"):
        unpack_evaluation(damaged, tmp_path / "d" / "eval")
    (first.directory / "episodes" / "FloorPlan1.jsonl").write_text("edited\n")
    with pytest.raises(EvalError, match="does not match its checksum"):
        pack_evaluation(first.directory, tmp_path / "edited")


def test_an_evaluation_missing_from_a_read_only_archive_runs_and_says_it_is_not_kept(
    tmp_path, floorplan1_tasks, monkeypatch
):
    """A read-only archive (a read-only checkout's tables/episodes) is never written: the evaluation
    it lacks runs in the runs folder, and the one line that would say it was packed says it was not."""
    import os

    archive = tmp_path / "archive"
    archive.mkdir()
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode, *a, **k: False if Path(p) == archive else real_access(p, mode, *a, **k)
    )
    lines = []
    config = EvalConfig("random_walk", kitchens=("FloorPlan1",), episodes_per_target=1, seed=3)
    run = evaluate(config, tmp_path / "runs", progress=lines.append, archive=archive)
    assert not any(archive.iterdir()) and (run.directory / "episodes" / "FloorPlan1.jsonl").is_file()
    assert lines[-1] == f"not packed: {archive} is read-only ({run.directory} keeps the evaluation)"


def test_an_evaluation_of_a_whole_split_packs_every_kitchen_of_it(tmp_path):
    """An evaluation that lists no kitchens covers its split's: packing it keeps every one of them
    (it once packed none, silently), and unpacking rebuilds them all."""
    from kgnavbench.archives import pack_evaluation, unpack_evaluation

    config = EvalConfig(method="random_walk", split="val", episodes_per_target=1)
    assert config.kitchens == ()
    run = evaluate(config, runs_dir=tmp_path / "a", progress=lambda line: None)
    packed = pack_evaluation(run.directory, tmp_path / "packed")
    rebuilt = unpack_evaluation(packed, tmp_path / "b" / "eval")
    kept = sorted(p.stem for p in (rebuilt / "episodes").glob("*.jsonl"))
    assert kept == sorted(kitchens_of_split("val")) and len(kept) == 5
    again = evaluate(config, runs_dir=tmp_path / "b", progress=lambda line: None)  # resumes every kitchen
    assert len(again.resumed) == 5 and again.summary == run.summary
