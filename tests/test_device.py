"""--device: auto is the CPU here (no GPU), cuda where there is none is one clear error, a run
records its device; a CUDA test runs where torch sees a GPU and skips itself elsewhere."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from kgnavbench import runs
from kgnavbench.cli import main
from kgnavbench.device import DeviceError, resolve
from kgnavbench.runs import train_method

NO_CUDA = not torch.cuda.is_available()
TINY = [
    "agents_per_kitchen=7", "n_steps=5", "hidden=32", "lstm=32", "log_every=280", "val_every=700",
    "val_kitchens=1", "val_episodes=1", "il_batch=4", "tse_batch=4", "threads=1", "il=true", "tse=true",
]  # fmt: skip


def test_device_names_resolve():
    assert resolve("cpu") == torch.device("cpu")
    assert resolve("auto").type == ("cpu" if NO_CUDA else "cuda")
    for bad in ("tpu", "cpu:1", "cuda:x", ""):
        with pytest.raises(DeviceError, match="unknown device"):
            resolve(bad)


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_cuda_without_a_gpu_is_one_clear_error(capsys, floorplan1_tasks, tmp_path):
    with pytest.raises(DeviceError, match="CUDA is not available"):
        resolve("cuda")
    for argv in (
        ["train", "--method", "lstm_a3c", "--frames", "100", "--device", "cuda", "--runs", str(tmp_path)],
        [
            "eval",
            "--method",
            "random_walk",
            "--kitchens",
            "FloorPlan1",
            "--episodes",
            "1",
            "--device",
            "cuda",
        ],
        ["table", "--preset", "smoke", "--device", "gpu", "--runs", str(tmp_path)],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("kgnavbench: error: ") and "device" in err[0], err
    assert not list(tmp_path.glob("train/*"))  # nothing written


def test_a_run_records_its_device(tmp_path, floorplan1_tasks):
    sets = dict(s.split("=") for s in TINY)
    run = train_method("lstm_a3c", sets, 140, 0, ("FloorPlan1",), tmp_path, progress=lambda line: None)
    assert json.loads((run / "config.json").read_text())["device"] == ("cpu" if NO_CUDA else "cuda")
    # the same call with --device cpu is the same run (auto resolved to the CPU here)
    if NO_CUDA:
        again = train_method(
            "lstm_a3c", sets, 140, 0, ("FloorPlan1",), tmp_path, progress=lambda line: None, device="cpu"
        )
        assert again == run


@pytest.mark.skipif(NO_CUDA, reason="no CUDA device on this machine")
def test_training_and_evaluation_on_cuda(tmp_path, floorplan1_tasks):
    """End to end on the GPU: a run trains, its checkpoint loads on the CPU, and a policy acts on CUDA."""
    sets = dict(s.split("=") for s in TINY)
    run = train_method(
        "kg_attention", sets, 1400, 0, ("FloorPlan1",), tmp_path, progress=lambda line: None, device="cuda"
    )
    ck = runs.load_checkpoint(run / "last.pt")
    assert ck["frames"] == 1400 and all(torch.isfinite(v).all() for v in ck["model"].values())
    from kgnavbench.env import parallel_env
    from kgnavbench.policy import LearnedPolicy

    env = parallel_env(kitchen="FloorPlan1", n_agents=3, features=True)
    observations, infos = env.reset(seed=0)
    policy = LearnedPolicy(run / "last.pt", device="cuda")
    actions = policy.act(observations, infos)
    assert set(actions) == set(env.agents) and all(0 <= a < 10 for a in actions.values())
    assert isinstance(np.int64(actions[env.agents[0]]), np.integer)
