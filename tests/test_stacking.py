"""Stage 17 — stacking: a row's seeds in one process. Each stacked seed's first update is its
single-seed first update (to float rounding) for every network stacking takes; a stacked job's
400-frame training writes recorded weights (the rollouts' lock-step pinned, every update, with cuts
at the cap and TSE); a killed stacked job
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
from test_train import (  # (pytest puts tests/ on the path)
    TINY,
    _sampled_weights_differ,
    _train_weight_runs,
    record_samples,
    tiny_options,
    tiny_run,
)

from kgnavbench import files, models, runs, train, zoo
from kgnavbench.cli import build_parser, main

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


def _fake_train_seeds(monkeypatch, tmp_path: Path) -> list[dict]:
    """runs.train_seeds replaced by one that records what the CLI asked for and trains nothing."""
    calls: list[dict] = []

    def fake(method, options, frames, seeds, **rest):
        calls.append({"method": method, "options": options, "frames": frames, "seeds": seeds})
        return [tmp_path / f"run-{s}" for s in seeds]

    monkeypatch.setattr(runs, "train_seeds", fake)
    return calls


def test_an_explicit_seed_with_seeds_is_refused_seed_0_too_and_no_seed_is_seed_0(
    capsys, tmp_path, monkeypatch
):
    calls = _fake_train_seeds(monkeypatch, tmp_path)
    for given in ("0", "3"):  # 0 was let through: the check read --seed's default 0 as none given
        argv = ["train", "--method", "lstm_a3c", "--seed", given, "--seeds", "1,2", "--runs", str(tmp_path)]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--seeds names every seed to train: not with --seed" in err, err
    assert calls == []
    assert main(["train", "--method", "lstm_a3c", "--runs", str(tmp_path)]) == 0
    assert main(["train", "--method", "lstm_a3c", "--seed", "0", "--runs", str(tmp_path)]) == 0
    assert [c["seeds"] for c in calls] == [(0,), (0,)]  # no --seed is seed 0, today's run


def test_the_same_seeds_in_another_order_are_the_same_stacked_job(capsys, tmp_path, monkeypatch):
    """The seeds are part of a stacked run's name: 2,1 and 1,2 must be one job, not a second training
    into new run folders with the same weights."""
    calls = _fake_train_seeds(monkeypatch, tmp_path)
    for seeds in ("2,1", "1,2", "2, 0,1"):
        assert main(["train", "--method", "lstm_a3c", "--seeds", seeds, "--runs", str(tmp_path)]) == 0
    assert [c["seeds"] for c in calls] == [(1, 2), (1, 2), (0, 1, 2)]
    plugin = runs.load_plugin("lstm_a3c")
    config = plugin.config({})
    names = {
        runs.run_directory("r", runs.run_record(plugin, config, 100, 1, ("FloorPlan1",), stacked=seeds))
        for seeds in (calls[0]["seeds"], calls[1]["seeds"])
    }
    assert len(names) == 1
    capsys.readouterr()
    assert main(["train", "--method", "lstm_a3c", "--seeds", "2,1,2", "--runs", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'2,1,2': a seed appears twice" in err, err
    assert len(calls) == 3


def test_preset_with_several_seeds_says_the_table_does_not_reuse_them(capsys, tmp_path, monkeypatch):
    calls = _fake_train_seeds(monkeypatch, tmp_path)
    argv = ["train", "--method", "lstm_a3c", "--preset", "quick", "--runs", str(tmp_path)]
    assert main([*argv, "--seeds", "0,1"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert (
        out[0].startswith("note: --seeds 0,1 trains stacked runs of their own") and "does not reuse" in out[0]
    )
    assert sum("does not reuse" in line for line in out) == 1
    for one in (["--seeds", "1"], ["--seed", "1"], []):  # one seed: the table's run, no note
        assert main([*argv, *one]) == 0
        assert "does not reuse" not in capsys.readouterr().out
    assert len(calls) == 4


def test_train_help_says_what_stacked_runs_are_and_what_stacking_measured(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    speed = (ROOT / "docs" / "speed.md").read_text()
    assert "Several --seeds train stacked runs, runs of their own that the table does not reuse" in text
    assert "faster than one by one" not in text and "Measured no faster on a CPU" in text
    for row, ratio in (("+IL+TSE", "0.97x"), ("+KG+Attention", "0.95x")):  # the numbers docs/speed.md has
        assert f"{ratio} ({row})" in text and f"| {row} |" in speed and f"| {ratio} |" in speed


def test_a_success_rule_that_is_none_names_only_the_rules_training_takes(capsys, tmp_path, monkeypatch):
    calls = _fake_train_seeds(monkeypatch, tmp_path)
    argv = ["train", "--method", "lstm_a3c", "--runs", str(tmp_path), "--set"]
    assert main([*argv, "success_rule=bogus"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "one of ('visible', 'destination') to train, not 'bogus'" in err, err
    assert "arrival" not in err
    monkeypatch.undo()  # the real train_seeds: arrival is refused by TrainOptions, as an evaluation rule
    assert main([*argv, "success_rule=arrival"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'arrival' is an evaluation rule" in err, err
    assert calls == []


def test_a_stacked_jobs_lines_each_say_their_seed_and_a_single_seeds_are_as_before(capsys, tmp_path):
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    argv = ["train", "--method", "lstm_a3c", "--frames", "70", "--kitchens", "FloorPlan1", *sets]
    assert main([*argv, "--seeds", "1,2", "--runs", str(tmp_path / "stacked")]) == 0
    lines = capsys.readouterr().out.splitlines()[:-2]  # (the last two: the run directories)
    assert lines and all(line.startswith(("seed 1: ", "seed 2: ")) for line in lines), lines
    for seed in (1, 2):
        ours = [line for line in lines if line.startswith(f"seed {seed}: ")]
        assert any("validation: SR" in line for line in ours) and any(" frames/s" in line for line in ours)
        assert ours[0].startswith(f"seed {seed}: training lstm_a3c") and "finished lstm_a3c" in ours[-1]
    assert main([*argv, "--seed", "1", "--runs", str(tmp_path / "alone")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("training lstm_a3c") and not any(line.startswith("seed ") for line in lines)


# A stacked job's arithmetic, pinned as test_train.py pins single runs' (the same two checks): +IL+TSE
# with 30-action episodes, so that the rollouts cut agents at the cap and relabel TSE windows, seeds 0
# and 1 in one process, 400 frames. Byte for byte where this machine has a recording (to add one:
# `python tests/test_stacking.py --record-weights` prints its entry), else sampled weights to
# test_train.WEIGHT_TOLERANCE of tests/recorded_stacked_weight_samples.json (the AVX-512 EPYC's).
STACKED_RUN = (("lstm_a3c", ("il=true", "tse=true", "episode_cap=30", "wrong_stop_penalty=0.05")),)
STACKED_SEEDS = ("--seeds", "0,1")
STACKED_NAMES = ["seed 0 of lstm_a3c il tse episode_cap=30, stacked", "seed 1, stacked"]
STACKED_SAMPLES_FILE = Path(__file__).with_name("recorded_stacked_weight_samples.json")
RECORDED_STACKED_WEIGHTS = {
    "AMD EPYC | avx avx2 fma f16c avx512f avx512dq avx512bw avx512vl avx512_vnni avx512_bf16"
    " | torch 2.13.0": (
        "80ff8313a9fe2c25f598abc3757f76624c5359441e89e2ede096e5dee24a5e4f",
        "7162808b0808587627453a329e537d4fecff2012d65324d7fb72833a9cf1a939",
    ),
}


def test_a_stacked_job_writes_the_recorded_weights(tmp_path, hermetic_cache):
    if torch.__version__.split("+")[0] != "2.13.0":
        pytest.skip("the recorded weights are torch 2.13.0's")
    if "avx2" not in (files.machine()["vector_flags"] or ()):
        pytest.skip("the recorded weights pin AVX2's vector paths, which this CPU does not have")
    got = _train_weight_runs(tmp_path, hermetic_cache, runs=STACKED_RUN, argv=STACKED_SEEDS)
    key = files.machine_key(files.machine())
    if key in RECORDED_STACKED_WEIGHTS:
        assert tuple(r["sha256"] for r in got) == RECORDED_STACKED_WEIGHTS[key], (
            f"the bytes recorded on {key}"
        )
    else:
        print(f"no byte recording for {key}: the tolerance check alone")
        assert not _sampled_weights_differ(got, STACKED_NAMES, STACKED_NAMES, STACKED_SAMPLES_FILE)


if __name__ == "__main__":  # python tests/test_stacking.py --record-weights [--samples]
    import tempfile

    if sys.argv[1:2] != ["--record-weights"]:
        sys.exit("usage: python tests/test_stacking.py --record-weights [--samples]")
    with tempfile.TemporaryDirectory() as folder:
        cache = Path(os.environ.get("KGNAVBENCH_CACHE") or Path.home() / ".cache" / "kgnavbench")
        recorded = _train_weight_runs(Path(folder), cache, runs=STACKED_RUN, argv=STACKED_SEEDS)
    print(f'    "{files.machine_key(files.machine())}": (')
    print("".join(f'        "{r["sha256"]}",\n' for r in recorded) + "    ),")
    if "--samples" in sys.argv:
        record_samples(recorded, STACKED_NAMES, STACKED_SAMPLES_FILE)
