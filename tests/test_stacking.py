"""Stage 17 — stacking: a row's seeds in one process. Each stacked seed's first update is its
single-seed first update (to float rounding) for every network stacking takes; a killed stacked job
resumes every seed to the weights of an unbroken one; a single seed's run keeps today's name; what
cannot stack is refused in one line."""

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
from test_train import TINY, tiny_options, tiny_run  # (pytest puts tests/ on the path)

from kgnavbench import models, runs, train, zoo
from kgnavbench.cli import main

ROOT = Path(__file__).resolve().parent.parent

# each network stacking takes: Table I's LSTM rows (no graph; the graph's control row's detections;
# +KG's and +KG+Attention's "nodes" readouts, the latter with one softmax per image and bounded scores)
CONFIGS = {
    "lstm": models.ModelConfig(lstm=32, hidden=32),
    "detections": models.ModelConfig(lstm=32, hidden=32, detections=True, gcn=16),
    "kg": models.ModelConfig(
        lstm=32, hidden=32, kg="mean", gcn=16, kg_readout="nodes", kg_edges="ppmi_top5", gcn_norm="pair"
    ),
    "kg_attention": models.ModelConfig(
        lstm=32,
        hidden=32,
        kg="attention",
        gcn=16,
        kg_readout="nodes",
        kg_edges="ppmi_top5",
        gcn_norm="pair",
        attention_over="each",
        attention_bound=2.0,
    ),  # fmt: skip
}


def _trainer(tmp_path: Path, seed: int, config: models.ModelConfig) -> train.Trainer:
    # IL and TSE on, and short episodes, so that the rollout ends episodes, cuts some at the cap and
    # relabels windows; a first update that has done all of it
    options = tiny_options(il=True, tse=True, episode_cap=4, n_steps=8, tse_batch=8)
    return train.Trainer(tiny_run(tmp_path / f"seed{seed}", seed=seed), options, config, True)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_each_stacked_seeds_first_update_is_its_single_seed_one(tmp_path, floorplan1_tasks, name):
    config = CONFIGS[name]
    alone = [_trainer(tmp_path / "alone", seed, config) for seed in (0, 1)]
    for t in alone:
        t.update()
    stacked = [_trainer(tmp_path / "stacked", seed, config) for seed in (0, 1)]
    # the same start: seeded weights, so the seeds differ from each other and match their twins
    first = [dict(t.model.net.named_parameters()) for t in stacked]
    assert not torch.equal(first[0]["policy.weight"], first[1]["policy.weight"])
    train.stacked_update(stacked)
    for a, s in zip(alone, stacked):
        assert a.frames == s.frames and a.updates == s.updates == 1
        assert a.stats["episodes"] == s.stats["episodes"] > 0  # the same actions, so the same episodes
        assert a.stats["losses_tse"] == s.stats["losses_tse"] == 1  # a TSE batch was relabelled
        assert torch.equal(a.model.covis.counts, s.model.covis.counts)
        for key in ("rl", "il", "tse"):
            assert s.stats[key] == pytest.approx(a.stats[key], rel=1e-4, abs=1e-5), key
        stacked_params = dict(s.model.net.named_parameters())
        for key, p in a.model.net.named_parameters():
            assert torch.allclose(p, stacked_params[key], rtol=1e-4, atol=1e-6), key
        # Adam moved every parameter that had a gradient
        moments = s.optimizer.state_dict()["state"]
        assert len(moments) == len(a.optimizer.state_dict()["state"])


def test_stacking_refuses_what_it_cannot_stack(capsys, tmp_path):
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    argv = ["train", "--method", "ff_a3c", "--frames", "70", "--kitchens", "FloorPlan1", "--seeds", "0,1"]
    assert main([*argv, "--runs", str(tmp_path), *sets]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "arch='ff'" in err and "one by one" in err, err
    argv = ["train", "--method", "lstm_a3c", "--seeds", "0,1", "--seed", "2", "--runs", str(tmp_path)]
    assert main(argv) == 2
    assert "not with --seed" in capsys.readouterr().err
    assert main(["train", "--method", "lstm_a3c", "--seeds", "1,1", "--runs", str(tmp_path)]) == 2
    assert "appears twice" in capsys.readouterr().err


def test_one_seed_is_todays_run_and_stacked_seeds_are_runs_of_their_own():
    plugin = runs.load_plugin("lstm_a3c")
    config = plugin.config({})
    alone = runs.run_record(plugin, config, 100, 1, ("FloorPlan1",))
    assert "stacked_seeds" not in alone  # the zoo's runs keep their names
    assert runs.run_record(plugin, config, 100, 1, ("FloorPlan1",), stacked=(1,)) == alone
    stacked = runs.run_record(plugin, config, 100, 1, ("FloorPlan1",), stacked=(0, 1))
    assert stacked["stacked_seeds"] == [0, 1]
    assert runs.run_directory("r", stacked) != runs.run_directory("r", alone)
    # and `table --trained` takes no stacked run for a table's (single-seed) job, nor the reverse
    assert zoo.record_differences(stacked, alone) == ["stacked_seeds"]
    assert zoo.record_differences(alone, alone) == []


def _train_seeds(root: Path, frames: int) -> list[str]:
    sets = [f"--set={k}={v}" for k, v in TINY.items()] + ["--set=tse=true", "--set=episode_cap=30"]
    cmd = [sys.executable, "-m", "kgnavbench", "train", "--method", "lstm_a3c", "--frames", str(frames)]
    return cmd + ["--kitchens", "FloorPlan1", "--runs", str(root), "--seeds", "0,1", *sets]


def test_a_killed_stacked_job_resumes_every_seed(tmp_path, hermetic_cache):
    """kill -9 after the first checkpoints, run the same command again: every seed resumes from its
    last.pt and ends with exactly the weights of an unbroken stacked job."""
    env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache)}
    whole = subprocess.run(_train_seeds(tmp_path / "a", 840), capture_output=True, text=True, env=env)
    assert whole.returncode == 0, whole.stderr
    runs_a = [Path(line) for line in whole.stdout.strip().splitlines()[-2:]]
    assert all((r / "finished.json").exists() for r in runs_a) and runs_a[0] != runs_a[1]
    assert [json.loads((r / "config.json").read_text())["stacked_seeds"] for r in runs_a] == [[0, 1]] * 2

    cmd = _train_seeds(tmp_path / "b", 840)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    runs_b = [tmp_path / "b" / "train" / r.name for r in runs_a]
    deadline = time.time() + 120
    while not all((r / "last.pt").exists() for r in runs_b) and proc.poll() is None:
        assert time.time() < deadline, "no checkpoint in 120 s"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    saved = [runs.load_checkpoint(r / "last.pt")["frames"] for r in runs_b]
    assert all(0 < f < 840 for f in saved) and not any((r / "finished.json").exists() for r in runs_b)
    again = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert again.returncode == 0, again.stderr
    for r, f in zip(runs_b, saved):
        assert f"resumed {r} from last.pt at {f:,} frames" in again.stdout
    for ra, rb in zip(runs_a, runs_b):
        a, b = runs.load_checkpoint(ra / "last.pt"), runs.load_checkpoint(rb / "last.pt")
        assert a["frames"] == b["frames"] == 840 and a["updates"] == b["updates"]
        for key in a["model"]:
            assert torch.equal(a["model"][key], b["model"][key]), (ra.name, key)
