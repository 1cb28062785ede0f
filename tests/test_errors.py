"""Every bad input the docs promise a clear error for: one line `kgnavbench: error: ...` naming the
problem, exit status 2, no traceback, and nothing half-written."""

from __future__ import annotations

import gzip
import json
import textwrap

import pytest

from kgnavbench import graph as graph_stage
from kgnavbench import kitchens, tasks
from kgnavbench.cli import main

SMALL = "FloorPlan25"  # the smallest kitchen (719 states): a damaged cache file is rebuilt in seconds


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *named: str) -> str:
    assert code == 2, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("kgnavbench: error: "), err
    assert "Traceback" not in err
    for name in named:
        assert name in lines[0], (name, lines[0])
    return lines[0]


def plugin(body: str, privileged: bool = False) -> str:
    head = 'DESCRIPTION = "a broken test plugin"\n' + ("PRIVILEGED = True\n" if privileged else "")
    return head + textwrap.dedent(body)


WALKER = """
class Policy:
    def reset(self, agent):
        {reset}
    def act(self, observations, infos):
        {act}
def make_policy(config, spec):
    return Policy()
"""

BROKEN_POLICIES = {
    "act_raises": (
        WALKER.format(reset="pass", act="raise RuntimeError('boom')"),
        "act() failed: RuntimeError",
    ),
    "reset_raises": (WALKER.format(reset="1 / 0", act="return {}"), "reset() failed: ZeroDivisionError"),
    "act_exits": (WALKER.format(reset="pass", act="import sys; sys.exit(3)"), "act() failed: SystemExit"),
    "act_base_exception": (
        "class Odd(BaseException):\n    pass\n" + WALKER.format(reset="pass", act="raise Odd('odd')"),
        "act() failed: Odd",
    ),
    "action_out_of_range": (WALKER.format(reset="pass", act="return {a: 10 for a in observations}"), "10"),
    "action_a_name": (
        WALKER.format(reset="pass", act="return {a: 'MoveAhead' for a in observations}"),
        "MoveAhead",
    ),
    "action_a_bool": (WALKER.format(reset="pass", act="return {a: True for a in observations}"), "True"),
    "action_a_float": (WALKER.format(reset="pass", act="return {a: 1.0 for a in observations}"), "1.0"),
    "actions_a_list": (WALKER.format(reset="pass", act="return [0] * len(observations)"), "not a dict"),
    "actions_missing": (WALKER.format(reset="pass", act="return {}"), "missing"),
    "peeks_at_the_expert": (
        WALKER.format(reset="pass", act="return {a: infos[a]['expert_action'] for a in observations}"),
        "infos['expert_action'], which only a plugin with PRIVILEGED",
    ),
    "peeks_at_the_state": (
        WALKER.format(reset="pass", act="return {a: infos[a]['state'] % 10 for a in observations}"),
        "infos['state'], which only a plugin with PRIVILEGED",
    ),
    "exits_on_import": ("import sys\nsys.exit('no')\n", "failed to import: SystemExit"),
    "an_exception_that_cannot_be_printed": (
        "class Mute(Exception):\n    def __str__(self):\n        raise ValueError('no words')\n"
        + WALKER.format(reset="pass", act="raise Mute()"),
        "act() failed: Mute: (an unprintable Mute)",
    ),
    "a_message_of_many_lines": (
        WALKER.format(reset="pass", act="raise RuntimeError('first\\nsecond\\nthird')"),
        "act() failed: RuntimeError: first",
    ),
}


@pytest.mark.parametrize("name", sorted(BROKEN_POLICIES))
def test_a_broken_plugin_names_its_file_and_writes_no_results(capsys, local, floorplan1_tasks, name):
    body, message = BROKEN_POLICIES[name]
    (local / f"{name}.py").write_text(plugin(body))
    runs = local.parent / "runs"
    code, out, err = run(
        capsys, "eval", "--method", name, "--kitchens", "FloorPlan1", "--episodes", "1", "--runs", str(runs)
    )
    assert_one_line_error(code, err, f"{name}.py", message)
    assert not list(runs.glob("eval/*/episodes/*"))  # nothing half-written


def test_a_privileged_plugin_may_read_the_expert(capsys, local, floorplan1_tasks):
    body = WALKER.format(reset="pass", act="return {a: infos[a]['expert_action'] for a in observations}")
    (local / "peeker.py").write_text(plugin(body, privileged=True))
    code, out, err = run(capsys, "eval", "--method", "peeker", "--kitchens", "FloorPlan1", "--episodes", "1")
    assert code == 0, err


OPTIONAL_CONFIG = """
from dataclasses import dataclass
DESCRIPTION = "options typed X | None"
@dataclass
class Config:
    cap: int | None = None
    rate: float | None = 0.5
def make_policy(config, spec):
    raise ValueError(f"cap={config.cap!r} rate={config.rate!r}")
"""


def test_options_typed_x_or_none(capsys, local):
    from kgnavbench.plugins import PluginError, load_plugin

    (local / "optional.py").write_text(OPTIONAL_CONFIG)
    p = load_plugin("optional")
    assert p.config({"cap": "5"}).cap == 5
    assert p.config({"cap": "none", "rate": "0.25"}) == p.config_class(cap=None, rate=0.25)
    assert p.config({"rate": "None"}).rate is None
    with pytest.raises(PluginError, match="cap='x' is not a int or none"):
        p.config({"cap": "x"})
    code, _, err = run(
        capsys, "eval", "--method", "optional", "--set", "rate=fast", "--kitchens", "FloorPlan1"
    )
    assert_one_line_error(code, err, "optional.py", "rate='fast'", "float or none")
    code, _, err = run(
        capsys, "eval", "--method", "optional", "--set", "rate=inf", "--kitchens", "FloorPlan1"
    )
    assert_one_line_error(code, err, "optional.py", "finite")


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "1e308,0.5"], "1e308"),
        (
            ["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "-1.0,0.5,1e300,0"],
            "1e300",
        ),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "random:100000000000"], "random:100000000000"),
        (["prepare", "--kitchens", ","], "--kitchens ','"),
        (["prepare", "--kitchens", ""], "--kitchens ''"),
        (["prepare", "--kitchens", "FloorPlan1,FloorPlan1"], "FloorPlan1 named twice"),
        (["eval", "--method", "oracle", "--kitchens", "FloorPlan4,,FloorPlan1"], "--kitchens"),
        (["eval", "--method", "oracle", "--kitchens", "FloorPlan1,FloorPlan1"], "named twice"),
        (["prepare", "--workers", "0"], "--workers"),
        (["prepare", "--workers", "-3"], "--workers"),
        (["eval", "--method", "oracle", "--episodes", "0"], "--episodes"),
        (["eval", "--method", "oracle", "--success-rule", "near"], "near"),
        (["eval", "--method", "nobody"], "nobody"),
        (["eval", "--method", "random_walk", "--set", "speed=3"], "speed"),
    ],
)
def test_bad_arguments(capsys, argv, named):
    code, out, err = run(capsys, *argv)
    assert_one_line_error(code, err, named)
    assert out == ""


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["train", "--method", "lstm_a3c", "--seed", "-1"], "--seed"),
        (["train", "--method", "lstm_a3c", "--seed", str(2**70)], str(2**70)),
        (["eval", "--method", "random_walk", "--seed", "-1"], "--seed"),
        (
            ["eval", "--method", "random_walk", "--split", "val", "--kitchens", "FloorPlan1"],
            "not in the 'val'",
        ),
        (["train", "--method", "lstm_a3c", "--set", "agents_per_kitchen=1000000000"], "at most 1024"),
        (["train", "--method", "lstm_a3c", "--set", "val_kitchens=6"], "val_kitchens must be at most 5"),
        (["train", "--method", "lstm_a3c", "--set", "val_episodes=101"], "val_episodes must be at most 100"),
        (["train", "--method", "lstm_a3c", "--record", "/nonexistent-folder/a.rrd"], "--record"),
        (["train", "--method", "lstm_a3c", "--record", "curves.txt"], ".rrd"),
    ],
)
def test_bad_input_is_refused_before_any_work(capsys, tmp_path, monkeypatch, argv, named):
    """Issue 17's probe: a traceback, a plugin blamed, an OOM or a silent clamp before; one line now,
    and no run directory."""
    monkeypatch.chdir(tmp_path)
    code, out, err = run(capsys, *argv)
    assert_one_line_error(code, err, named)
    assert not list(tmp_path.glob("runs/*/*"))


def test_unwritable_output_folders_are_refused_before_any_work(capsys, tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    for argv in (
        ["train", "--method", "lstm_a3c", "--frames", "10", "--runs", str(blocker / "runs")],
        ["table", "--preset", "smoke", "--runs", str(tmp_path / "runs"), "--out", str(blocker / "t")],
        ["figures", "--runs", str(tmp_path / "runs"), "--out", str(blocker / "f")],
    ):
        code, _, err = run(capsys, *argv)
        assert_one_line_error(code, err, "cannot write there", str(blocker))
    assert blocker.read_text() == "x" and not list(tmp_path.glob("runs/*"))


def test_figures_from_a_trained_folder_that_is_not_there_is_one_line(capsys, tmp_path):
    out, runs = tmp_path / "figures", tmp_path / "runs"
    code, _, err = run(
        capsys, "figures", "--trained", str(tmp_path / "nowhere"), "--runs", str(runs), "--out", str(out)
    )
    assert_one_line_error(code, err, "--trained", "no such folder")
    assert not out.exists() and not runs.exists()  # refused before any folder is made


def test_figures_of_a_row_the_preset_has_not_is_one_line(capsys, tmp_path):
    out, runs = tmp_path / "figures", tmp_path / "runs"
    code, _, err = run(
        capsys, "figures", "--preset", "smoke", "--row", "nope", "--runs", str(runs), "--out", str(out)
    )
    assert_one_line_error(code, err, "preset 'smoke' has no row 'nope'")
    assert not runs.exists() and not out.exists()  # refused before any folder is made


def test_an_unknown_preset_is_one_line_naming_the_spec_presets_in_every_command(capsys, tmp_path):
    """train, table and figures all refuse it with the same line (TableSpec.preset), before work."""
    out, runs = tmp_path / "out", tmp_path / "runs"
    for argv in (
        ["train", "--method", "lstm_a3c", "--preset", "huge"],
        ["table", "--preset", "huge", "--out", str(out)],
        ["figures", "--preset", "huge", "--out", str(out)],
        ["figures", "--preset", "huge", "--row", "+KG", "--out", str(out)],
    ):
        code, _, err = run(capsys, *argv, "--runs", str(runs))
        assert_one_line_error(code, err, "unknown preset 'huge'", "has smoke, quick")
        assert not runs.exists() and not out.exists(), argv


def test_version(capsys):
    code, out, _ = run(capsys, "--version")
    assert code == 0 and out.startswith("kgnavbench 0.")


def test_a_train_hook_that_raises_or_exits_names_its_file(capsys, local):
    for name, body in (("raiser", "raise RuntimeError('boom')"), ("exiter", "import sys; sys.exit(4)")):
        (local / f"{name}.py").write_text(
            plugin(f"def make_policy(config, spec):\n    pass\ndef train(config, run):\n    {body}\n")
        )
        code, _, err = run(capsys, "train", "--method", name, "--frames", "10", "--kitchens", "FloorPlan1")
        line = assert_one_line_error(code, err, f"{name}.py", "train()")
        assert ("RuntimeError: boom" in line) if name == "raiser" else ("sys.exit(4)" in line)


def test_json_stays_json_when_a_plugin_prints_and_cells_are_empty(capsys, local, floorplan1_tasks):
    """A plugin that prints goes to stderr under --json; cells without episodes are null, not NaN."""
    body = WALKER.format(
        reset="print('resetting', agent)", act="print('acting'); return {a: 9 for a in observations}"
    )
    (local / "chatty.py").write_text(plugin(body))
    code, out, err = run(
        capsys, "eval", "--method", "chatty", "--kitchens", "FloorPlan1", "--episodes", "1", "--json"
    )
    assert code == 0, err
    record = json.loads(out)  # strict: json.loads would take NaN, so look for it too
    assert "NaN" not in out and "acting" in err
    assert record["summary"]["seen_seen/static"]["episodes"] > 0
    from kgnavbench.arguments import json_safe

    assert (
        json.dumps(json_safe({"sr": float("nan"), "x": [float("inf"), 1.5]}))
        == '{"sr": null, "x": [null, 1.5]}'
    )


def test_ctrl_c_in_a_policy_is_one_line_and_resumable(capsys, local, floorplan1_tasks):
    body = WALKER.format(reset="pass", act="raise KeyboardInterrupt")
    (local / "interrupted.py").write_text(plugin(body))
    code, out, err = run(
        capsys, "eval", "--method", "interrupted", "--kitchens", "FloorPlan1", "--episodes", "1"
    )
    assert code == 130 and err.strip().startswith("kgnavbench: interrupted") and "Traceback" not in err


def test_an_edited_results_file_is_refused_not_summed(capsys, tmp_path, floorplan1_tasks):
    argv = ["eval", "--method", "random_walk", "--kitchens", "FloorPlan1", "--episodes", "1"]
    argv += ["--runs", str(tmp_path), "--json"]
    code, out, err = run(capsys, *argv)
    assert code == 0, err
    (episodes,) = (tmp_path / "eval").glob("*/episodes/FloorPlan1.jsonl")
    assert (episodes.parent / "FloorPlan1.jsonl.sha256").read_text().endswith("  FloorPlan1.jsonl\n")
    rows = [json.loads(line) for line in episodes.read_text().splitlines()]
    rows[0]["success"] = not rows[0]["success"]  # well formed, but not what was written
    episodes.write_text("".join(json.dumps(r) + "\n" for r in rows))
    code, _, err = run(capsys, *argv)
    assert_one_line_error(code, err, "FloorPlan1.jsonl", "checksum")


def test_a_task_file_entry_missing_fields(capsys, monkeypatch):
    record = json.loads(json.dumps(tasks.load_task_file()))
    del record["kitchens"]["FloorPlan1"]["targets"][0]["destination"]
    monkeypatch.setattr(tasks, "load_task_file", lambda path=tasks.TASKS_FILE: record)
    code, _, err = run(capsys, "targets", "FloorPlan1")
    assert_one_line_error(code, err, "FloorPlan1", "malformed", "destination")
    record["kitchens"]["FloorPlan1"]["targets"][0]["destination"] = "12"
    code, _, err = run(capsys, "targets", "FloorPlan1")
    assert_one_line_error(code, err, "malformed", "'12'")


@pytest.mark.parametrize(
    ("damage", "named"),
    [
        (lambda r: r.update(grid="0.25"), "'grid'"),
        (lambda r: r["objects"][0].update(openable="yes"), "'openable'"),
        (lambda r: r["objects"][3].update(footprint=[[["a", 0]]]), "'footprint'"),
        (lambda r: r.update(reachable=[[0.5, 1]]), "'reachable'"),
        (lambda r: r.pop("room"), "'room'"),
    ],
)
def test_a_kitchen_file_with_a_wrong_type(capsys, tmp_path, monkeypatch, damage, named):
    with gzip.open(kitchens.KITCHEN_DIR / "FloorPlan1.json.gz", "rt") as f:
        record = json.load(f)
    damage(record)
    (tmp_path / "FloorPlan1.json.gz").write_bytes(gzip.compress(json.dumps(record).encode()))
    monkeypatch.setattr(kitchens, "KITCHEN_DIR", tmp_path)
    kitchens.load_kitchen.cache_clear()
    try:
        code, _, err = run(capsys, "kitchens", "FloorPlan1")
        assert_one_line_error(code, err, "FloorPlan1.json.gz", "corrupt", named)
    finally:
        kitchens.load_kitchen.cache_clear()


def test_a_cache_folder_that_cannot_be_written(capsys, tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    monkeypatch.setenv("KGNAVBENCH_CACHE", str(blocker / "cache"))
    code, _, err = run(capsys, "prepare", "--kitchens", "FloorPlan4", "--workers", "1")
    assert_one_line_error(code, err, "cannot write the state-graph cache", "KGNAVBENCH_CACHE")
    assert blocker.read_text() == "x"


def test_a_runs_folder_that_cannot_be_written(capsys, tmp_path, floorplan1_tasks):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    argv = [
        "eval",
        "--method",
        "oracle",
        "--kitchens",
        "FloorPlan1",
        "--episodes",
        "1",
        "--runs",
        str(blocker),
    ]
    code, _, err = run(capsys, *argv)
    assert_one_line_error(code, err, "cannot write", "--runs")
    assert blocker.read_text() == "x"


def test_json_output_stays_json_when_the_cache_is_rebuilt(capsys, tmp_path, monkeypatch):
    """A damaged cache file's notice goes to stderr; stdout is exactly one JSON document. (In SMALL, the
    smallest kitchen: the damaged file is rebuilt in seconds.)"""
    graph_stage.state_graph(SMALL)  # built (in seconds) where no test built it yet
    root = graph_stage.cache_dir()
    graph_path, _ = graph_stage._cache_paths(SMALL, graph_stage.VIEW_SIZE, root)
    saved = graph_path.read_bytes()
    try:
        graph_path.write_bytes(b"garbage")
        argv = ["eval", "--method", "oracle", "--kitchens", SMALL, "--episodes", "1", "--json"]
        code, out, err = run(capsys, *argv, "--runs", str(tmp_path))
        assert code == 0, err
        assert "cannot be trusted" in err
        assert json.loads(out)["summary"]["all/all"]["sr"] == 100.0
    finally:
        graph_path.write_bytes(saved)


@pytest.mark.parametrize(
    "damage, named",
    [
        ("scrambled", "does not match its checksum"),  # rows permuted: a readable file, same shape and type
        ("no checksum", "no checksum"),
        ("not finite", "not finite"),  # with a checksum that matches: what was written must make sense
    ],
)
def test_a_cached_feature_file_is_checked_not_trusted(capsys, damage, named, floorplan1_tasks):
    import numpy as np

    from kgnavbench import encoder
    from kgnavbench.files import checksum_path, write_with_checksum

    path = encoder.features_path("FloorPlan1")
    good = np.array(encoder.state_features("FloorPlan1"))
    if damage == "not finite":  # rewritten with a checksum that matches it
        bad = good.copy()
        bad[3, 7] = np.nan
        write_with_checksum(path, lambda f: np.save(f, bad))
    else:  # written over in place, rows reversed: the good file's checksum stays beside it, or goes
        np.save(path, good[::-1])
        if damage == "no checksum":
            checksum_path(path).unlink()
    capsys.readouterr()
    rebuilt = encoder.state_features("FloorPlan1")
    err = capsys.readouterr().err
    assert "cannot be trusted" in err and named in err, err
    assert np.array_equal(np.array(rebuilt), good)
    assert encoder.state_features("FloorPlan1") is not None and capsys.readouterr().err == ""


@pytest.mark.parametrize(
    "damage, named",
    [
        ("transition out of range", "next points outside"),
        ("object out of range", "vis_obj points outside"),
        ("no checksum", "no checksum"),
    ],
)
def test_a_cached_state_graph_is_checked_not_trusted(capsys, damage, named):
    """A state-graph file whose transitions point past its states is rebuilt, even with a checksum
    that matches it (a step would index outside the tables: a traceback, or a wrong episode)."""
    import numpy as np

    graph_stage.state_graph(SMALL)  # built (in seconds) where no test built it yet
    root = graph_stage.cache_dir()
    graph_path, _ = graph_stage._cache_paths(SMALL, graph_stage.VIEW_SIZE, root)
    with np.load(graph_path) as z:
        arrays = {k: z[k] for k in z.files}
    good = graph_stage.state_graph(SMALL)
    if damage == "transition out of range":
        arrays["next"][5, 0] = len(arrays["cell"]) + 10
    elif damage == "object out of range":
        arrays["vis_obj"][0] = 10_000
    if damage == "no checksum":
        from kgnavbench.files import checksum_path

        checksum_path(graph_path).unlink()
    else:
        from kgnavbench.files import write_with_checksum

        write_with_checksum(graph_path, lambda f: np.savez(f, **arrays))
    capsys.readouterr()
    rebuilt = graph_stage.state_graph(SMALL)
    err = capsys.readouterr().err
    assert "cannot be trusted" in err and named in err, err
    assert np.array_equal(rebuilt.next_state, good.next_state)
    assert graph_stage.load_graph(SMALL) is not None and capsys.readouterr().err == ""


CHDIR = WALKER.format(reset="pass", act="return {a: 9 for a in observations}").replace(
    "def make_policy(config, spec):\n", "def make_policy(config, spec):\n    import os; os.chdir('/')\n"
)


def test_paths_are_resolved_once_whatever_a_plugin_does(capsys, local, floorplan1_tasks, monkeypatch):
    """A plugin that changes the working directory in make_policy cannot split one evaluation between
    two folders: --runs (relative here) was made absolute when the command started."""
    (local / "wanderer.py").write_text(plugin(CHDIR))
    monkeypatch.chdir(local.parent)
    code, out, err = run(
        capsys, "eval", "--method", "wanderer", "--kitchens", "FloorPlan1,FloorPlan2", "--episodes", "1",
        "--runs", "relative-runs", "--json",
    )  # fmt: skip
    assert code == 0, err
    monkeypatch.chdir(local.parent)
    episodes = sorted(p.name for p in (local.parent / "relative-runs").glob("eval/*/episodes/*.jsonl"))
    assert episodes == ["FloorPlan1.jsonl", "FloorPlan2.jsonl"]


@pytest.mark.parametrize(
    ("content", "named"),
    [
        (b"[protocol]\nx = " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply"),
        (b'[protocol]\nsuccess_rule = "\xff\xfe"\n', "not UTF-8"),
        (b"# " + b"x" * 1_100_000 + b"\n", "more than a spec's"),
    ],
    ids=["deep", "not-utf8", "huge"],
)
def test_a_spec_file_that_is_no_spec(capsys, tmp_path, content, named):
    spec = tmp_path / "bad.toml"
    spec.write_bytes(content)
    code, out, err = run(capsys, "table", "--spec", str(spec), "--runs", str(tmp_path / "runs"))
    assert_one_line_error(code, err, "bad.toml", named)


@pytest.mark.parametrize("identity", ["5", "[]", "null", '{"identity": 5}', '{"identity": []}'])
def test_an_evaluations_config_json_of_any_shape_is_one_line(capsys, tmp_path, floorplan1_tasks, identity):
    argv = ["eval", "--method", "random_walk", "--kitchens", "FloorPlan1", "--episodes", "1"]
    argv += ["--runs", str(tmp_path)]
    assert run(capsys, *argv)[0] == 0
    (config,) = tmp_path.glob("eval/*/config.json")
    config.write_text(identity)
    code, out, err = run(capsys, *argv)
    assert_one_line_error(code, err, "holds an evaluation with another")


SLEEPER = WALKER.format(reset="pass", act="import time; time.sleep(3600)")


def test_a_policy_that_never_returns_is_named_and_timed_out(capsys, local, floorplan1_tasks, monkeypatch):
    """eval says which kitchen and step it is waiting on, and --step-timeout ends the run with one line
    naming the plugin, the call and the place."""
    from kgnavbench import plugins

    monkeypatch.setattr(plugins, "WAIT_NOTE", 0.3)
    monkeypatch.setattr(plugins, "step_timeout", None)
    (local / "sleeper.py").write_text(plugin(SLEEPER))
    argv = ["eval", "--method", "sleeper", "--kitchens", "FloorPlan1", "--episodes", "1"]
    code = main([*argv, "--runs", str(local.parent / "runs"), "--step-timeout", "1"])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if not line.startswith("kgnavbench: still waiting")]
    assert_one_line_error(code, "\n".join(lines) + "\n", "sleeper.py", "act() did not return within 1 s")
    assert "FloorPlan1, step 1" in lines[0]
    assert "kgnavbench: still waiting for act() of" in err and "(FloorPlan1, step 1)" in err
    assert main([*argv, "--step-timeout", "0"]) == 2
    assert "no time limit" in capsys.readouterr().err


def test_methods_lists_a_plugin_that_blocks_at_import_without_waiting(capsys, local, monkeypatch):
    from kgnavbench import cli

    monkeypatch.setattr(cli, "METHODS_IMPORT_TIMEOUT", 1.0)
    (local / "stuck.py").write_text("import time\ntime.sleep(3600)\n")
    code, out, err = run(capsys, "methods")
    assert code == 0
    (line,) = [line for line in out.splitlines() if "stuck" in line]
    assert "BROKEN" in line and "its import did not return within 1 s" in line


def test_every_error_class_of_the_package_has_the_one_base_that_main_catches():
    """Each stage's error class derives from KgnavbenchError, which `cli.main` catches once (one line,
    exit status 2); none is left out to end in a traceback."""
    import importlib
    import inspect
    import pkgutil

    import kgnavbench
    from kgnavbench.errors import KgnavbenchError

    classes = {}
    for info in pkgutil.iter_modules(kgnavbench.__path__):
        if info.name == "__main__":  # runs the command line when imported
            continue
        module = importlib.import_module(f"kgnavbench.{info.name}")
        for name, value in vars(module).items():
            if (
                inspect.isclass(value)
                and issubclass(value, Exception)
                and not issubclass(value, Warning)  # a warning is no error
                and value.__module__ == module.__name__
            ):
                classes[f"{info.name}.{name}"] = value
    assert len(classes) >= 19, sorted(classes)
    outside = sorted(name for name, cls in classes.items() if not issubclass(cls, KgnavbenchError))
    assert not outside, f"error classes without the base: {outside}"


def test_a_time_out_the_plugin_catches_is_raised_again_when_it_returns():
    """Plugin code that catches the PluginTimeout and returns does not get its step through."""
    import time

    from kgnavbench import plugins

    def swallows_the_time_out():
        try:  # noqa: SIM105 - what a careless plugin does
            time.sleep(5)
        except BaseException:  # noqa: BLE001
            pass
        return {}

    timed_out = pytest.raises(plugins.PluginTimeout, match="act\\(\\) did not return within 0.2 s")
    with timed_out, plugins.watched("careless.py", "act()", limit=0.2):
        swallows_the_time_out()


@pytest.mark.parametrize(
    "defeat",
    [
        "signal.signal(signal.SIGALRM, signal.SIG_IGN); time.sleep(30)",
        "\n".join(
            ["while True:", "    try:", "        time.sleep(30)", "    except BaseException:", "        pass"]
        ),
    ],
    ids=["ignores_sigalrm", "catches_every_time_out"],
)
def test_a_plugin_that_defeats_the_time_out_ends_the_process_with_one_line(defeat, tmp_path):
    """A step that neither returns nor lets the time-out through is ended by the watchdog: exit 2, one
    line naming the plugin and the step, within the limit and its grace."""
    import subprocess
    import sys
    import time

    script = tmp_path / "defeat.py"
    script.write_text(
        "import signal, time\nfrom kgnavbench import plugins\nplugins.WATCHDOG_GRACE = 0.5\n"
        "with plugins.watched('defiant.py', 'act()', 'FloorPlan1, step 1', limit=0.3):\n"
        + textwrap.indent(defeat, "    ")
        + "\nprint('went on')\n"
    )
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert "went on" not in done.stdout
    assert_one_line_error(
        2, done.stderr, "defiant.py", "act() did not return within 0.3 s", "FloorPlan1, step 1"
    )
    assert time.monotonic() - t0 < 20


def test_one_watchdog_thread_serves_every_watched_call_and_nested_blocks_keep_their_deadlines():
    """Under --step-timeout every plugin call is watched: one thread for all of them, not one each; an
    inner block is held to the earlier of its own deadline and the enclosing block's, whose deadline
    its release gives back."""
    import threading

    from kgnavbench import plugins

    with plugins.watched("a.py", "act()", limit=30.0):
        threads = threading.active_count()
        watchdog = plugins._WATCHDOG.thread
        outer = plugins._WATCHDOG.deadline
        for _ in range(50):
            with plugins.watched("a.py", "act()", limit=30.0):
                pass
        with plugins.watched("b.py", "act()", limit=60.0):  # an inner block never extends the outer's
            assert plugins._WATCHDOG.deadline == outer
        with plugins.watched("b.py", "act()", limit=1.0):  # nor shortens it past its own end
            assert plugins._WATCHDOG.deadline[0] < outer[0] and "b.py" in plugins._WATCHDOG.deadline[1]
        assert threading.active_count() == threads
        assert plugins._WATCHDOG.thread is watchdog and watchdog.is_alive()
        assert plugins._WATCHDOG.deadline == outer
    assert plugins._WATCHDOG.deadline is None


def test_watching_plugin_code_restores_the_callers_timer_and_handler():
    """A caller's own ITIMER_REAL timer and SIGALRM handler survive a watched call (evaluate_policy's
    callers may have one)."""
    import signal
    import time

    from kgnavbench import plugins

    def mine(signum, frame):
        pass

    before = signal.signal(signal.SIGALRM, mine)
    try:
        signal.setitimer(signal.ITIMER_REAL, 30.0, 7.0)
        with plugins.watched("a.py", "act()", limit=5.0):
            time.sleep(0.2)
        remaining, interval = signal.getitimer(signal.ITIMER_REAL)
        assert signal.getsignal(signal.SIGALRM) is mine
        assert 29.0 < remaining < 29.9 and interval == 7.0
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, before)


def test_options_that_cannot_work_together_or_a_missing_folder_are_refused_before_any_work(capsys, tmp_path):
    """--workers with --ray (refused before connecting: nothing listens at the address); checkpoints
    with no runs folder, or a figure OpenCV cannot write (refused before evaluating anything, not
    after the CSV is written); checkpoints that find no run writes nothing and says so, exit 2."""
    code = main(
        ["table", "--preset", "smoke", "--ray", "127.0.0.2:1", "--workers", "3", "--runs", str(tmp_path)]
    )
    assert_one_line_error(code, capsys.readouterr().err, "--workers", "--ray")
    csv_path = tmp_path / "c.csv"
    argv = ["checkpoints", "--preset", "smoke", "--csv", str(csv_path)]
    code = main([*argv, "--runs", str(tmp_path / "nope")])
    assert_one_line_error(code, capsys.readouterr().err, "--runs", "no such folder")
    code = main([*argv, "--runs", str(tmp_path), "--figure", str(tmp_path / "f.xyz")])
    assert_one_line_error(code, capsys.readouterr().err, "--figure", "f.xyz")
    code = main([*argv, "--runs", str(tmp_path)])  # an empty runs folder: no run, no CSV, no "wrote"
    err = assert_one_line_error(code, capsys.readouterr().err, "no finished run", "nothing written")
    assert "wrote" not in err and not csv_path.exists()


def test_a_command_run_inside_another_checkout_is_refused_naming_both(tmp_path, monkeypatch, capsys):
    """From a worktree or copy of the repository with another checkout's kgnavbench installed, the
    code, the default spec and tables/ would be that other checkout's while zoo/ and runs/ are this
    folder's: one line naming both checkouts and the way out, nothing run. In the package's own
    checkout (any folder of it) and outside any checkout, commands run."""
    from kgnavbench.cli import PACKAGE_CHECKOUT

    other = tmp_path / "worktree"
    (other / "kgnavbench").mkdir(parents=True)
    (other / "kgnavbench" / "__init__.py").write_text("")
    (other / "tables").mkdir()
    (other / "tables" / "table1.toml").write_text("")
    (other / "zoo").mkdir()
    for where in (other, other / "zoo"):
        monkeypatch.chdir(where)
        assert main(["table", "--preset", "smoke", "--jobs"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"in the checkout {other}" in err, err
        assert f"{PACKAGE_CHECKOUT}'s" in err and "python -m kgnavbench" in err
    assert main(["table", "--help"]) == 0  # help answers anywhere
    capsys.readouterr()
    for where in (PACKAGE_CHECKOUT / "docs", tmp_path):
        monkeypatch.chdir(where)
        assert main(["methods"]) == 0
        capsys.readouterr()
    # an installed package (pip install ., not editable) is no checkout: it runs inside any clone
    import kgnavbench.cli as cli

    monkeypatch.setattr(cli, "PACKAGE_CHECKOUT", tmp_path / "venv" / "lib" / "site-packages")
    monkeypatch.chdir(other)
    assert main(["methods"]) == 0
    capsys.readouterr()


def test_figures_curves_only_without_a_trained_folder_is_one_line(capsys, tmp_path):
    """The seeds' curves are drawn from shipped runs, never trained for: --curves-only needs --trained."""
    out, runs = tmp_path / "figures", tmp_path / "runs"
    code, _, err = run(capsys, "figures", "--curves-only", "--runs", str(runs), "--out", str(out))
    assert_one_line_error(code, err, "--curves-only", "--trained")
    assert not out.exists() and not runs.exists()
