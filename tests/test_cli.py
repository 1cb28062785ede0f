"""The `kgnavbench` command line: every command on a tiny budget, and its errors."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from kgnavbench.cli import main
from kgnavbench.kitchens import KITCHEN_NAMES, kitchen_summary, load_kitchen
from kgnavbench.world import ACTIONS, World

ROOT = Path(__file__).resolve().parent.parent
EGG = "Egg|-02.04|+00.81|+01.24"
FRIDGE = "Fridge|-02.10|+00.00|+01.07"
# Facing the fridge's door side (its front points to +x) from 1.1 m away, looking down 30 degrees.
FRIDGE_START = "-1.0,1.0,270,30"
START = "-1.0,0.5,270,30"


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def step_lines(out: str) -> list[str]:
    """The per-step lines of a text walk (they start with the step index)."""
    return [line for line in out.splitlines() if line.split() and line.split()[0].isdigit()]


def cell(text: str) -> tuple[int, int]:
    x, z = (float(v) for v in text.split(",")[:2])
    return (round(x / 0.25), round(z / 0.25))


def test_start_poses_are_reachable():
    reachable = World("FloorPlan1").reachable
    assert cell(START) in reachable
    assert cell(FRIDGE_START) in reachable


# ----------------------------------------------------------------------------------------------------
# kitchens


def test_kitchens_table_lists_the_30_kitchens_in_order(capsys):
    code, out, err = run(capsys, "kitchens")
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert "reachable cells" in lines[0] and "openable receptacles" in lines[0]
    names = [line.split()[0] for line in lines[1:]]
    assert names == list(KITCHEN_NAMES) == [f"FloorPlan{i}" for i in range(1, 31)]
    for line, name in zip(lines[1:], KITCHEN_NAMES, strict=True):
        summary = kitchen_summary(load_kitchen(name))
        assert line.split() == [str(v) for v in summary.values()]


def test_kitchens_json_matches_the_table(capsys):
    code, out, _ = run(capsys, "kitchens", "--json")
    assert code == 0
    rows = json.loads(out)
    assert [r["name"] for r in rows] == list(KITCHEN_NAMES)
    assert set(rows[0]) == {"name", "reachable_cells", "objects", "hidden_objects", "openable_receptacles"}
    assert all(r["reachable_cells"] > 0 and r["objects"] > 0 for r in rows)


def test_kitchen_objects_json_has_the_egg_in_the_fridge(capsys):
    code, out, _ = run(capsys, "kitchens", "FloorPlan1", "--json")
    assert code == 0
    rows = json.loads(out)
    assert [r["id"] for r in rows] == [o.id for o in load_kitchen("FloorPlan1").objects]
    egg = next(r for r in rows if r["id"] == EGG)
    assert egg == {"id": EGG, "type": "Egg", "parent": FRIDGE, "hidden": True}
    fridge = next(r for r in rows if r["id"] == FRIDGE)
    assert fridge["parent"] is None and fridge["hidden"] is False


def test_kitchen_objects_table(capsys):
    code, out, _ = run(capsys, "kitchens", "FloorPlan1")
    assert code == 0
    egg_line = next(line for line in out.splitlines() if line.startswith(EGG))
    assert egg_line.split() == [EGG, "Egg", FRIDGE, "yes"]
    fridge_line = next(line for line in out.splitlines() if line.startswith(FRIDGE))
    assert fridge_line.split() == [FRIDGE, "Fridge", "-", "no"]


def test_console_entry_runs_as_a_module():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, "-m", "kgnavbench", "kitchens"],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert len(proc.stdout.splitlines()) == 31  # header + 30 kitchens
    assert "FloorPlan30" in proc.stdout


# ----------------------------------------------------------------------------------------------------
# walk


def test_walk_prints_each_step_and_writes_views_and_map(capsys, tmp_path):
    out_dir = tmp_path / "walk"
    actions = ["RotateRight", "MoveAhead", "LookUp", "RotateLeft", "MoveBack"]
    code, out, err = run(
        capsys,
        "walk",
        "--kitchen",
        "FloorPlan1",
        "--start",
        START,
        "--actions",
        ",".join(actions),
        "--size",
        "64",
        "--out",
        str(out_dir),
    )
    assert code == 0, err
    lines = step_lines(out)
    assert len(lines) == len(actions) + 1
    assert lines[0].split()[:4] == ["0", "(start)", "ok", "-1.00,0.50,270,30"]
    assert [line.split()[1] for line in lines[1:]] == actions
    # RotateRight: heading 270 -> 0; the step's pose is printed after the action
    assert lines[1].split()[3] == "-1.00,0.50,0,30"
    assert f"{len(actions)} steps" in out.splitlines()[-1] and str(out_dir) in out.splitlines()[-1]
    for step in range(len(actions) + 1):
        image = cv2.imread(str(out_dir / f"view_{step:03d}.png"))
        assert image is not None and image.shape == (64, 64, 3)
    top = cv2.imread(str(out_dir / "map.png"))
    assert top is not None and top.shape == (300, 300, 3)  # the map is at least 300 px


def test_walk_json_lines(capsys):
    code, out, err = run(
        capsys,
        "walk",
        "--kitchen",
        "FloorPlan1",
        "--start",
        START,
        "--actions",
        "LookDown,LookDown,LookDown",
        "--json",
    )
    assert code == 0
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["step"] for r in records] == [0, 1, 2, 3]
    assert set(records[0]) == {"step", "action", "success", "pose", "open_receptacle", "visible"}
    assert records[0]["action"] is None and records[0]["success"] is True
    assert records[0]["pose"] == {"x": -1.0, "z": 0.5, "heading": 270, "pitch": 30}
    # pitch 30 -> 60, then no further: the last two LookDowns fail
    assert [r["success"] for r in records[1:]] == [True, False, False]
    assert records[-1]["pose"]["pitch"] == 60
    assert "3 steps, 2 failed" in err  # the summary keeps stdout pure JSON lines


def test_walk_opens_the_fridge_and_shows_the_egg(capsys):
    code, out, _ = run(
        capsys,
        "walk",
        "--kitchen",
        "FloorPlan1",
        "--start",
        FRIDGE_START,
        "--actions",
        "OpenObject,LookUp",
        "--json",
    )
    assert code == 0
    start, opened, looked = (json.loads(line) for line in out.splitlines())
    assert start["open_receptacle"] is None and EGG not in start["visible"]
    assert opened["action"] == "OpenObject" and opened["success"] is True
    assert opened["open_receptacle"] == FRIDGE
    assert EGG in opened["visible"]
    # any action other than Stop closes the fridge again
    assert looked["open_receptacle"] is None and EGG not in looked["visible"]


def test_walk_text_shows_the_open_fridge(capsys):
    code, out, _ = run(
        capsys, "walk", "--kitchen", "FloorPlan1", "--start", FRIDGE_START, "--actions", "OpenObject"
    )
    assert code == 0
    opened = step_lines(out)[1].split()
    assert opened[:5] == ["1", "OpenObject", "ok", "-1.00,1.00,270,30", FRIDGE]
    assert EGG in opened[5:]


def test_walk_random_actions_are_deterministic(capsys):
    args = ["walk", "--kitchen", "FloorPlan1", "--actions", "random:5", "--seed", "7"]
    first = run(capsys, *args)
    second = run(capsys, *args)
    assert first[0] == 0 and first == second
    rng = random.Random(7)
    expected = [rng.choice(ACTIONS) for _ in range(5)]
    assert [line.split()[1] for line in step_lines(first[1])] == ["(start)", *expected]
    other = run(capsys, *args[:-1], "8")
    assert step_lines(other[1]) != step_lines(first[1])


def test_walk_default_start_is_the_world_pose(capsys):
    code, out, _ = run(capsys, "walk", "--kitchen", "FloorPlan1", "--actions", "Stop", "--json")
    assert code == 0
    records = [json.loads(line) for line in out.splitlines()]
    pose = World("FloorPlan1").pose
    assert records[0]["pose"] == {"x": pose.x, "z": pose.z, "heading": pose.heading, "pitch": pose.pitch}
    assert records[1]["action"] == "Stop" and records[1]["pose"] == records[0]["pose"]


# ----------------------------------------------------------------------------------------------------
# bad input: exit 2, one line naming the problem, no traceback


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["kitchens", "FloorPlan99"], "FloorPlan99"),
        (["walk", "--kitchen", "Kitchen1", "--actions", "MoveAhead"], "Kitchen1"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead,Jump"], "Jump"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "random:x"], "random:x"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "0,0,0,0"], "0.00, 0.00"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "north"], "north"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "-1.1,0.5"], "-1.1,0.5"),
        (
            ["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "-1.0,0.5,45"],
            "heading 45",
        ),
        (
            ["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "-1.0,0.5,0,90"],
            "pitch 90",
        ),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "-1.0,0.5,nan"], "nan"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--start", "-1.0,0.5,270.5"], "270.5"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--size", "8"], "8"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--size", "2048"], "2048"),
        (["walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead", "--size", "big"], "big"),
        (["walk", "--actions", "MoveAhead"], "--kitchen"),
        (["fly"], "fly"),
    ],
)
def test_bad_input_exits_2_with_one_line(capsys, argv, named):
    code, out, err = run(capsys, *argv)
    assert code == 2
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("kgnavbench: error: ")
    assert named in lines[0]
    assert "Traceback" not in err


def test_bad_action_fails_before_anything_runs(capsys, tmp_path):
    out_dir = tmp_path / "never"
    code, out, _ = run(
        capsys, "walk", "--kitchen", "FloorPlan1", "--actions", "MoveAhead,Jump", "--out", str(out_dir)
    )
    assert code == 2 and out == ""
    assert not out_dir.exists()


def test_unusable_output_folder(capsys, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    code, _, err = run(
        capsys, "walk", "--kitchen", "FloorPlan1", "--actions", "Stop", "--out", str(blocker / "x")
    )
    assert code == 2
    assert err.startswith("kgnavbench: error: ") and str(blocker / "x") in err


def test_help_exits_0(capsys):
    code, out, _ = run(capsys, "walk", "--help")
    assert code == 0 and "--actions" in out


def test_walk_with_a_placement_seed(capsys):
    args = ["walk", "--kitchen", "FloorPlan1", "--actions", "RotateLeft", "--placement-seed", "3", "--json"]
    first = run(capsys, *args)
    assert first[0] == 0 and first == run(capsys, *args)
    assert [json.loads(line)["step"] for line in first[1].splitlines()] == [0, 1]


# ----------------------------------------------------------------------------------------------------
# prepare, targets, methods, eval


def test_prepare_reports_the_cached_kitchen(capsys, floorplan1_tasks):
    code, out, err = run(capsys, "prepare", "--kitchens", "FloorPlan1", "--workers", "1")
    assert code == 0, err
    assert out.splitlines()[0].split()[:3] == ["FloorPlan1", str(floorplan1_tasks.graph.n_states), "states"]
    assert "1 kitchens" in out.splitlines()[-1]


def test_targets_lists_the_egg_as_actionable(capsys, floorplan1_tasks):
    code, out, err = run(capsys, "targets", "FloorPlan1", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["split"] == "train" and len(data["targets"]) == len(floorplan1_tasks.targets)
    egg = next(t for t in data["targets"] if t["target"] == EGG)
    assert egg["kind"] == "actionable" and egg["opened"] == FRIDGE and egg["episodes"] == 100


def test_methods_lists_the_plugins(capsys):
    code, out, err = run(capsys, "methods")
    assert code == 0, err
    assert {line.split()[0] for line in out.splitlines()[1:]} >= {"oracle", "random_walk"}


def test_eval_prints_the_table_i_layout(capsys, tmp_path, floorplan1_tasks):
    argv = [
        "eval",
        "--method",
        "oracle",
        "--kitchens",
        "FloorPlan1",
        "--episodes",
        "1",
        "--runs",
        str(tmp_path),
    ]
    code, out, err = run(capsys, *argv)
    assert code == 0, err
    rows = [line for line in out.splitlines() if line.startswith("| seen kitchens / seen targets")]
    assert [r.split("|")[2].strip() for r in rows] == ["static", "actionable", "all"]
    assert all(r.split("|")[4].strip() == "100.00" and r.split("|")[5].strip() == "100.00" for r in rows)
    assert f"{len(floorplan1_tasks.targets)} episodes" in out.splitlines()[-1]
    code, out, err = run(capsys, *argv, "--json")
    assert code == 0 and json.loads(out)["summary"]["all/all"]["sr"] == 100.0


def test_eval_random_walk_shows_the_papers_row(capsys, tmp_path, floorplan1_tasks):
    code, out, err = run(
        capsys, "eval", "--method", "random_walk", "--kitchens", "FloorPlan1", "--episodes", "1",
        "--runs", str(tmp_path), "--set", "stop_probability=0.5",
    )  # fmt: skip
    assert code == 0, err
    assert "static seen/seen 1.56, actionable seen/seen 0.23, static seen/unseen 14.86" in out
    assert "stop_probability=0.5" in out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["eval", "--method", "nope"], "unknown method 'nope'"),
        (["eval", "--method", "random_walk", "--set", "speed=2"], "unknown option 'speed'"),
        (["eval", "--method", "random_walk", "--set", "speed"], "not KEY=VALUE"),
        (["eval", "--method", "oracle", "--kitchens", "FloorPlan99"], "FloorPlan99"),
        (["eval", "--method", "oracle", "--episodes", "0"], "0 is not in 1..100"),
        (["eval", "--method", "oracle", "--split", "dev"], "invalid choice: 'dev'"),
        (["targets", "Kitchen7"], "Kitchen7"),
    ],
)
def test_eval_errors_name_the_problem(capsys, tmp_path, argv, message):
    code, out, err = run(capsys, *argv, *(["--runs", str(tmp_path)] if argv[0] == "eval" else []))
    assert code == 2
    assert err.startswith("kgnavbench: error: ") and message in err
    assert not list(tmp_path.iterdir())  # nothing written


def test_every_inconsistency_of_a_commands_options_is_reported_at_once(capsys, tmp_path):
    """arguments.verify: one check per command gathers every problem of its options into one
    `kgnavbench: error:` line, before anything runs."""
    argv = ["table", "--preset", "smoke", "--runs", str(tmp_path / "runs"), "--train-only"]
    argv += ["--archive", str(tmp_path / "missing"), "--ray-node-ip", "127.0.0.2", "--row", "IL"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("kgnavbench: error: ")
    for said in (
        "--row picks the rows of a table to assemble",
        "--archive keeps evaluations; --train-only runs none",
        "--archive " + str(tmp_path / "missing") + ": no such folder",
        "--ray-node-ip is this machine's address",
    ):
        assert said in err, said
    assert not (tmp_path / "runs").exists()  # nothing ran
    argv = [
        "eval",
        "--method",
        "random_walk",
        "--checkpoint",
        "last",
        "--record",
        "x.txt",
        "--video",
        "y.avi",
    ]
    assert main([*argv, "--runs", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "give --run DIR too; --record " in err and "must end in .rrd; --video " in err and ".mp4" in err
