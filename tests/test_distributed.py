"""torchrun data-parallel training on CPU (gloo): two ranks hold bit-identical weights after every
update, the run records its world size, and a run killed with kill -9 resumes to the weights of an
unbroken two-rank run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from kgnavbench import runs

TINY = {
    "agents_per_kitchen": "7",
    "n_steps": "5",
    "hidden": "32",
    "lstm": "32",
    "log_every": "140",
    "val_every": "700",
    "val_kitchens": "1",
    "val_episodes": "1",
    "il_batch": "4",
    "tse_batch": "4",
    "threads": "1",
    "il": "true",
    "tse": "true",
    "episode_cap": "30",
}
FRAMES = 2100  # 15 updates of 14 agents x 5 steps (7 agents on each rank)


def _torchrun(runs: Path) -> list[str]:
    torchrun = str(Path(sys.executable).parent / "torchrun")
    cmd = [
        torchrun,
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "kgnavbench",
        "train",
        "--method",
        "lstm_a3c",
    ]
    cmd += ["--frames", str(FRAMES), "--kitchens", "FloorPlan1,FloorPlan2", "--runs", str(runs)]
    return cmd + [f"--set={k}={v}" for k, v in TINY.items()]


def _tree(pid: int) -> list[int]:
    """pid and every process below it, from /proc."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += children.get(p, [])
    return out


def test_two_gloo_ranks_stay_identical_and_resume_after_kill_9(tmp_path, hermetic_cache):
    env = {
        **os.environ,
        "KGNAVBENCH_CACHE": str(hermetic_cache),
        "KGNAVBENCH_CHECK_REPLICAS": "1",  # every update compares the ranks' weights, or fails the run
        "OMP_NUM_THREADS": "1",
    }
    whole = subprocess.run(_torchrun(tmp_path / "a"), capture_output=True, text=True, env=env, timeout=300)
    assert whole.returncode == 0, whole.stderr[-3000:]
    lines = whole.stdout.strip().splitlines()
    run_a = Path(lines[-1])
    assert "14 agents on 2 ranks" in whole.stdout and lines.count(str(run_a)) == 1  # rank 0 speaks
    assert json.loads((run_a / "config.json").read_text())["world_size"] == 2
    a = runs.load_checkpoint(run_a / "last.pt")
    assert a["frames"] == FRAMES and len(a["ranks"]) == 2
    # the ranks stepped different agents with different generators
    assert not torch.equal(a["ranks"][0]["agents"]["state"], a["ranks"][1]["agents"]["state"])

    # kill -9 the whole torchrun group after a checkpoint, start it again: the same end
    run_b = tmp_path / "b" / "runs" / "train" / run_a.name
    proc = subprocess.Popen(
        _torchrun(tmp_path / "b" / "runs"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )
    deadline = time.time() + 240
    while not (run_b / "last.pt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    for pid in _tree(proc.pid):  # torchrun and its workers (they run in sessions of their own)
        os.kill(pid, signal.SIGKILL)
    proc.wait()
    saved = runs.load_checkpoint(run_b / "last.pt")["frames"]
    assert 0 < saved < FRAMES and not (run_b / "finished.json").exists()
    again = subprocess.run(
        _torchrun(tmp_path / "b" / "runs"), capture_output=True, text=True, env=env, timeout=300
    )
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"at {saved:,} frames" in again.stdout
    b = runs.load_checkpoint(run_b / "last.pt")
    assert b["frames"] == FRAMES and a["updates"] == b["updates"]
    for key in a["model"]:
        assert torch.equal(a["model"][key], b["model"][key]), key
    assert torch.equal(a["covis"]["counts"], b["covis"]["counts"])
    for rank in range(2):
        assert a["ranks"][rank]["rng"]["numpy"] == b["ranks"][rank]["rng"]["numpy"]
        assert torch.equal(a["ranks"][rank]["agents"]["state"], b["ranks"][rank]["agents"]["state"])


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(
    ("env", "message"),
    [
        ({"RANK": "1", "WORLD_SIZE": "1"}, "RANK=1 is no rank of WORLD_SIZE=1"),
        ({"RANK": "abc"}, "must be whole numbers"),
        ({"RANK": "0", "WORLD_SIZE": "2"}, "WORLD_SIZE=2 without MASTER_ADDR"),
        (
            {"RANK": "0", "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "KGNAVBENCH_RANK_TIMEOUT": "2"},
            "the ranks did not all join within 2 s",
        ),
    ],
    ids=["rank-outside-world", "not-a-number", "no-torchrun", "a-rank-missing"],
)
def test_stray_or_broken_rank_variables_are_one_line(capsys, tmp_path, monkeypatch, env, message):
    """RANK / WORLD_SIZE outside torchrun, or ranks that never all join: one line and exit 2, never a
    silent exit 0 that trains nothing (RANK=1 WORLD_SIZE=1) or torch's 30-minute wait."""
    from kgnavbench.cli import main

    for key in ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT", "LOCAL_RANK"):
        monkeypatch.delenv(key, raising=False)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    if "MASTER_ADDR" in env:
        monkeypatch.setenv("MASTER_PORT", str(_free_port()))
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    command = ["train", "--method", "lstm_a3c", "--frames", "70", "--kitchens", "FloorPlan1"]
    start = time.perf_counter()
    assert main([*command, "--runs", str(tmp_path), *sets]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert time.perf_counter() - start < 60
    assert not list(tmp_path.glob("train/*/last.pt"))
