"""The record stage: episodes and training curves written to .rrd and read back with rerun's own reader,
the viewer command, exact t-SNE, and the OpenCV figures."""

import csv
import json
import re
import subprocess
import sys
import textwrap
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from rerun.chunk import RrdReader

from kgnavbench import figures, plots, record
from kgnavbench.plots import FigureError
from kgnavbench.plugins import PluginError
from kgnavbench.record import RecordError

EPISODE_ENTITIES = {
    "/view",
    "/target",
    "/map",
    "/episode",
    "/action",
    "/scalars/reward",
    "/scalars/return",
    "/scalars/collisions",
    "/scalars/failed",
    "/scalars/success",
}

# a policy that explains itself as the learned KG policy does: the top-3 attended types after act()
EXPLAINING_PLUGIN = """
DESCRIPTION = "MoveAhead forever, attending to three fixed types"

class Policy:
    def reset(self, agent):
        self.acts = 0

    def act(self, observations, infos):
        self.acts += 1
        if self.acts > FAIL_AFTER:
            raise RuntimeError("broken on purpose")
        return {a: 0 for a in observations}

    def explain(self, agent):
        return {"attention": [("Fridge", 0.5), ("Egg", 0.3), ("Apple", 0.2), ("Bowl", 0.0)]}

def make_policy(config, spec):
    return Policy()
"""


def rows_per_entity(path) -> Counter:
    """Rows per entity path of the recording store (blueprints aside), summed over its chunks."""
    reader = RrdReader(path)
    rows: Counter = Counter()
    for chunk in reader.stream().to_chunks():
        if not chunk.is_static:
            rows[str(chunk.entity_path)] += chunk.num_rows
    return rows


def column(path, entity: str, name: str) -> list:
    """The values of one column (a timeline or a component) of an entity, in chunk order."""
    values = []
    for chunk in RrdReader(path).stream().to_chunks():
        if str(chunk.entity_path) == entity:
            batch = chunk.to_record_batch()
            values += batch.column(batch.schema.names.index(name)).to_pylist()
    return values


def test_two_random_walk_episodes_read_back(tmp_path, floorplan1_tasks):
    path = tmp_path / "walk.rrd"
    # Stop never drawn: both episodes run to the cap, so every count below is exact
    out = record.record_episodes(
        "random_walk", {"stop_probability": "0"}, path, kitchens=["FloorPlan1"], episodes=2, max_steps=6
    )
    assert out["episodes"] == 2 and out["steps"] == 12
    assert list(tmp_path.iterdir()) == [path]  # no .partial left behind
    reader = RrdReader(path)
    assert [s.application_id for s in reader.recordings()] == ["kgnavbench_episodes"]
    assert reader.blueprints(), "the layout travels with the file"

    rows = rows_per_entity(path)
    assert set(rows) == EPISODE_ENTITIES  # no attention: random_walk has no explain()
    # each episode: its start, then one row per action
    assert rows["/view"] == rows["/map"] == 12 + 2
    assert rows["/target"] == 2
    assert rows["/episode"] == 2 * 2  # at the start, and with the outcome
    for entity in EPISODE_ENTITIES - {"/view", "/map", "/target", "/episode"}:
        assert rows[entity] == 12, entity
    assert sorted(column(path, "/view", "step")) == list(range(14))
    assert sorted(column(path, "/view", "episode")) == [0] * 7 + [1] * 7
    assert sorted(column(path, "/action", "step")) == [s for s in range(14) if s not in (0, 7)]
    assert sorted(column(path, "/target", "step")) == [0, 7]


def test_attention_of_an_explaining_policy_is_logged(tmp_path, floorplan1_tasks, monkeypatch):
    monkeypatch.chdir(tmp_path)  # ./baselines of the working directory holds a researcher's plugins
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "explaining.py").write_text(EXPLAINING_PLUGIN.replace("FAIL_AFTER", "99"))
    path = tmp_path / "out" / "kg.rrd"
    record.record_episodes("explaining", {}, path, kitchens=["FloorPlan1"], episodes=1, max_steps=5)
    rows = rows_per_entity(path)
    assert rows["/attention"] == 5  # a line per action: the top 3 with their weights
    top3 = {"/attention_weight/Fridge", "/attention_weight/Egg", "/attention_weight/Apple"}
    assert set(rows) == EPISODE_ENTITIES | {"/attention"} | top3
    assert all(rows[e] == 5 for e in top3)


def test_a_failing_episode_leaves_no_file(tmp_path, floorplan1_tasks, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "breaks.py").write_text(EXPLAINING_PLUGIN.replace("FAIL_AFTER", "3"))
    with pytest.raises(PluginError, match="broken on purpose"):
        record.record_episodes("breaks", {}, tmp_path / "x.rrd", kitchens=["FloorPlan1"], max_steps=9)
    assert list(tmp_path.glob("x.rrd*")) == []
    with pytest.raises(RecordError, match=r"\.rrd"):
        record.record_episodes("random_walk", {}, tmp_path / "x.txt", kitchens=["FloorPlan1"])


def test_training_curves_read_back(tmp_path):
    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text(
        "frames,seconds,frames_per_s,updates,episodes,mean_reward,mean_return,success_rate,"
        "rl_loss,il_loss,tse_loss,val_sr,val_spl\n"
        "1000,1.0,1000,10,3,-0.01,-0.5,0.0,1.2,0.8,,,\n"
        "2000,2.0,1000,20,7,-0.005,-0.2,0.1,1.0,0.6,,12.5,8.0\n"
        "3000,3.1,968,30,12,0.02,0.4,0.2,0.9,0.5,,,\n"
    )
    path = tmp_path / "train.rrd"
    out = record.record_training(csv_path, path)
    assert out["rows"] == 3
    rows = rows_per_entity(path)
    assert rows["/training/reward/mean_reward"] == 3
    assert rows["/training/loss/rl_loss"] == 3
    assert rows["/training/validation/val_sr"] == rows["/training/validation/val_spl"] == 1  # empty cells
    assert "/training/loss/tse_loss" not in rows  # a column with no value at all
    assert len(rows) == 11
    assert column(path, "/training/validation/val_sr", "frames") == [2000]
    assert column(path, "/training/progress/episodes", "frames") == [1000, 2000, 3000]

    (tmp_path / "bad.csv").write_text("frames,mean_reward\n1000,oops\n")
    with pytest.raises(RecordError, match="line 2"):
        record.record_training(tmp_path / "bad.csv", tmp_path / "bad.rrd")
    (tmp_path / "nofr.csv").write_text("steps,mean_reward\n1000,1\n")
    with pytest.raises(RecordError, match="frames"):
        record.record_training(tmp_path / "nofr.csv", tmp_path / "bad.rrd")


def test_view_without_display_says_how(tmp_path, monkeypatch, capsys):
    with pytest.raises(RecordError, match="no such recording"):
        record.view(tmp_path / "missing.rrd")
    (tmp_path / "notes.rrd").write_text("not a recording")
    with pytest.raises(RecordError, match="not a rerun recording"):
        record.view(tmp_path / "notes.rrd")

    path = tmp_path / "t.rrd"
    (tmp_path / "m.csv").write_text("frames,mean_reward\n1,0.5\n")
    record.record_training(tmp_path / "m.csv", path)
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert record.view(path) == 0
    said = capsys.readouterr().out
    assert "no display" in said and "rerun t.rrd" in said and "--serve-web" in said

    # with a display: the viewer runs on the file (stubbed here: no window in a test)
    calls = []
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(record.subprocess, "run", lambda cmd, check: calls.append(cmd) or _Done(3))
    assert record.view(path) == 3
    assert calls[0][-1] == str(path) and "rerun" in " ".join(calls[0][:-1])


class _Done:
    def __init__(self, returncode):
        self.returncode = returncode


def test_tsne_is_deterministic_and_keeps_clusters_apart():
    g = torch.Generator().manual_seed(1)
    a = torch.randn(20, 10, generator=g)
    b = torch.randn(20, 10, generator=g) + 20.0
    x = torch.cat([a, b])
    y = figures.tsne(x, perplexity=8, iterations=300, seed=3)
    assert y.shape == (40, 2) and torch.isfinite(y).all()
    assert torch.equal(y, figures.tsne(x.clone(), perplexity=8, iterations=300, seed=3))
    assert not torch.equal(y, figures.tsne(x, perplexity=8, iterations=300, seed=4))
    assert figures.tsne(x, dims=3, iterations=50).shape == (40, 3)
    # every point is nearer to its own cluster's centre than to the other's
    ca, cb = y[:20].mean(0), y[20:].mean(0)
    assert ((y[:20] - ca).norm(dim=1) < (y[:20] - cb).norm(dim=1)).all()
    assert ((y[20:] - cb).norm(dim=1) < (y[20:] - ca).norm(dim=1)).all()
    spread = max((y[:20] - ca).norm(dim=1).max(), (y[20:] - cb).norm(dim=1).max())
    assert (ca - cb).norm() > 2 * spread
    with pytest.raises(ValueError):
        figures.tsne(torch.zeros(5))


def _is_figure(path, size=(1000, 600)) -> bool:
    """A PNG of `size` with more than a blank page on it: text and axes, and coloured data marks."""
    img = cv2.imread(str(path))
    assert img is not None, path
    assert img.shape == (size[1], size[0], 3)
    ink = (img < 250).any(axis=2).mean()
    colour = (img.max(axis=2).astype(int) - img.min(axis=2) > 60).sum()
    return ink > 0.003 and colour > 50


def test_figures_are_pngs_of_the_right_size(tmp_path):
    labels = ["Random walk", "LSTM A3C", "+KG+Attention (ours)"]
    p = plots.bar_line_figure(
        labels,
        [12.0, 5.5, 1.7],
        [3.0, float("nan"), 44.1],
        tmp_path / "a.png",
        "t",
        "collisions",
        "last view %",
    )
    assert _is_figure(p)
    pts = np.array([[0.0, 0.0], [1.0, 2.0], [3.0, -1.0]])
    assert _is_figure(plots.scatter_figure(pts, ["Fridge", "Egg", "Apple"], tmp_path / "b.png", "t-SNE"))
    series = {"a": ([0, 1000, 2000], [0.0, 0.2, 0.5]), "b": ([0, 1000, 2000], [0.1, float("nan"), 0.7])}
    assert _is_figure(plots.curves_figure(series, tmp_path / "c.png", "curves", "frames", "SR"))
    assert _is_figure(
        plots.curves_figure(series, tmp_path / "d.png", "small", "x", "y", size=(640, 400)), (640, 400)
    )
    with pytest.raises(FigureError):
        plots.bar_line_figure(labels, [1.0], [1.0], tmp_path / "e.png", "t", "a", "b")


def test_recording_costs_nothing_when_off():
    # the other stages and the CLI must not import rerun (nor this stage) until a recording is asked for
    code = textwrap.dedent(
        """
        import sys
        import kgnavbench.cli, kgnavbench.evaluate, kgnavbench.env
        print("rerun" in sys.modules, "kgnavbench.record" in sys.modules)
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def _episode(column: str, collisions: int, shown: bool, kitchen: str = "FloorPlan26") -> dict:
    return {
        "kitchen": kitchen,
        "target": "Apple|+00.00|+01.00|+00.00",
        "kind": "static",
        "column": column,
        "start": 1,
        "max_steps": 1000,
        "success": shown,
        "path_length": 12,
        "shortest_path": 10,
        "collisions": collisions,
        "last_view_shows_target": shown,
        "episode_length": 13,
    }


def _eval_run(directory, episodes: list[dict]):
    (directory / "episodes").mkdir(parents=True)
    by_kitchen: dict[str, list[str]] = {}
    for e in episodes:
        by_kitchen.setdefault(e["kitchen"], []).append(json.dumps(e))
    for kitchen, lines in by_kitchen.items():
        (directory / "episodes" / f"{kitchen}.jsonl").write_text("\n".join(lines) + "\n")
    return directory


def test_paper_figures_from_runs(tmp_path, floorplan1_tasks, monkeypatch):
    from kgnavbench.runs import train_method

    seen = [_episode("seen_seen", 9, False, "FloorPlan1")]
    outcomes = ((4, False), (2, True), (6, False), (0, False))  # (collisions, last view shows target)
    walk_episodes = seen + [_episode("unseen_kitchens", c, s) for c, s in outcomes]
    walk = _eval_run(tmp_path / "eval" / "walk", walk_episodes)
    ours = _eval_run(
        tmp_path / "eval" / "ours",
        seen + [_episode("unseen_kitchens", c, s, "FloorPlan27") for c, s in ((1, True), (0, True))],
    )
    ff = _eval_run(tmp_path / "eval" / "ff", seen)  # no unseen kitchens: no bar
    assert figures.unseen_kitchen_stats(figures.read_episodes(walk)) == (3.0, 25.0)
    assert figures.unseen_kitchen_stats(figures.read_episodes(ours)) == (0.5, 100.0)
    assert figures.unseen_kitchen_stats(figures.read_episodes(ff)) is None

    options = {
        "agents_per_kitchen": "7",
        "n_steps": "5",
        "hidden": "16",
        "lstm": "16",
        "gcn": "16",
        "log_every": "200",
        "val_every": "200",
        "val_kitchens": "1",
        "val_episodes": "1",
        "threads": "1",
    }
    run = train_method(
        "kg_attention",
        options,
        frames=200,
        kitchens=("FloorPlan1",),
        runs_dir=tmp_path,
        progress=lambda line: None,
    )
    rows = [
        ("Random walk", None, str(walk)),
        ("FF A3C", None, str(ff)),
        ("+KG+Attention", str(run), str(ours)),
    ]
    notes = []
    seed_runs = [("+KG+Attention", [run, run], True)]  # one run as two seeds: their mean is the run
    paths = figures.figures(rows, tmp_path / "figures", progress=notes.append, seed_runs=seed_runs)
    names = [p.name for p in paths]
    assert names == [
        "collisions_unseen.png", "tsne_gcn.png", "attention_example.png", "attention_episode.png",
        "training_curves.png", "training_reward.png",
        "training_curves_seeds.png", "training_curves_seeds.csv",
    ]  # fmt: skip
    assert len(notes) == 1 and "no run logged success_rate" in notes[0]  # 200 frames: no episode ended
    notes.clear()
    paths = paths[:-1]  # the figures, each checked below
    step = figures.attention_step("kg_attention", run, row="+KG+Attention")
    steps = len(step["episode"][: figures.EPISODE_STEPS_SHOWN])
    sizes = {
        "tsne_gcn.png": figures.TSNE_SIZE,
        "attention_example.png": figures.ATTENTION_SIZE,
        "attention_episode.png": (1200, 160 + 20 * steps),  # one line per step
        "training_curves_seeds.png": figures.SEED_PANEL_SIZE,  # the validation panel alone
    }
    for p in paths:
        assert _is_figure(p, sizes.get(p.name, plots.FIGURE_SIZE)), p

    # the attention example's step: weights over the types in the view or the target, summing to 1;
    # a softmax over all nodes weighs the others too ("in neither"), and figures() prefers the former
    places = {place for _, _, place in step["attended"]}
    assert places and "in neither" not in places and "+KG+Attention (" in step["caption"]
    assert sum(w for _, w, _ in step["attended"]) == pytest.approx(1.0, abs=1e-4)
    # and every step of its episode: the action taken and the (at most) 3 most attended types
    from kgnavbench.world import ACTIONS

    for action, top in step["episode"]:
        assert action in ACTIONS and 1 <= len(top) <= 3
        assert [w for _, w, _ in top] == sorted((w for _, w, _ in top), reverse=True)
    all_nodes = train_method(
        "kg_attention",
        {**options, "attention_nodes": "all", "kg_readout": "pooled"},  # the pooled reading only
        frames=200,
        kitchens=("FloorPlan1",),
        runs_dir=tmp_path,
        progress=lambda line: None,
    )
    step = figures.attention_step("kg_attention", all_nodes)
    assert len(step["attended"]) == 125 and "in neither" in {p for _, _, p in step["attended"]}
    chosen = []
    monkeypatch.setattr(figures, "attention_step", lambda *a, **k: chosen.append(a[1]) or step)
    figures.figures(
        [*rows, ("all nodes", str(all_nodes), str(ours))], tmp_path / "both", progress=notes.append
    )
    assert chosen == [Path(run)]

    # the GCN features the t-SNE embeds: the checkpoint's network over its own co-visibility graph
    h, adjacency = figures.gcn_node_features(figures._kg_checkpoint(run)[0])
    assert h.shape == (125, 16) and adjacency.sum() > 0

    # without a KG run or a training run: the figures that need them are skipped, with a note
    notes.clear()
    paths = figures.figures(rows[:2], tmp_path / "fewer", progress=notes.append)
    assert [p.name for p in paths] == ["collisions_unseen.png"]
    assert len(notes) == 5 and "tsne_gcn.png skipped" in notes[0] and "attention" in notes[1]
    assert "training_curves_seeds.png skipped" in notes[4]  # no row has its seeds' runs

    with pytest.raises(FigureError, match="no such evaluation run directory"):
        figures.figures([("LSTM A3C", None, str(tmp_path / "missing"))], tmp_path / "x")
    with pytest.raises(FigureError, match="no such training run directory"):
        figures.figures([("LSTM A3C", str(tmp_path / "gone"), str(ours))], tmp_path / "x")
    (ff / "episodes" / "FloorPlan1.jsonl").write_text("{not json\n")
    with pytest.raises(FigureError, match="line 1"):
        figures.figures(rows, tmp_path / "x")
    assert not (tmp_path / "x").exists()  # bad input fails before any figure is written


def test_the_attention_figure_refuses_what_it_cannot_draw(tmp_path):
    view = np.zeros((84, 84, 3), np.uint8)
    path = figures.attention_figure(
        view, view, [("Fridge", 0.7, "in the view"), ("Mug", 0.3, "in both")], tmp_path / "a.png", "t", "c"
    )
    assert _is_figure(path, figures.ATTENTION_SIZE)
    for attended, named in (([], "at least one"), ([("Mug", 0.5, "nowhere")], "'Mug'")):
        with pytest.raises(FigureError, match=named):
            figures.attention_figure(view, view, attended, tmp_path / "b.png", "t", "c")
        assert not (tmp_path / "b.png").exists()


def test_figures_of_table_takes_each_rows_first_seed(tmp_path, monkeypatch):
    from types import SimpleNamespace

    from kgnavbench import jobs, table, table_spec

    spec = table_spec.load_spec()
    runs = {}
    for name in ("walk", "ours"):
        runs[name] = _eval_run(tmp_path / name, [_episode("unseen_kitchens", 2, name == "ours")])
    result = SimpleNamespace(
        rows=[
            SimpleNamespace(row=spec.rows[0], train_runs=[""], eval_runs=[str(runs["walk"]), "seed 1"]),
            SimpleNamespace(row=spec.rows[-1], train_runs=[""], eval_runs=[str(runs["ours"])]),
        ]
    )
    calls = []
    monkeypatch.setattr(table, "run_table", lambda *args, progress: calls.append((*args, progress)) or result)
    notes = []
    paths = figures.figures_of_table("smoke", tmp_path / "runs", tmp_path / "figs", progress=notes.append)
    assert [p.name for p in paths] == ["collisions_unseen.png"]
    assert calls == [(spec, "smoke", tmp_path / "runs", notes.append)]
    assert len(notes) == 5  # no training runs: the t-SNE, the attention and the three curves are skipped

    # --trained: the runs come from that folder (table.Sources), never trained
    taken = []
    monkeypatch.setattr(
        table,
        "run_table",
        lambda *args, progress, device, sources, rows_named: taken.append(sources) or result,
    )
    figures.figures_of_table(
        "smoke", tmp_path / "runs", tmp_path / "figs", progress=notes.append, trained=tmp_path
    )
    assert taken == [jobs.Sources(tmp_path)]

    # --row: those rows only, as a partial table takes them
    named = []
    monkeypatch.setattr(
        table,
        "run_table",
        lambda *args, progress, device, sources, rows_named: (
            named.append((device, sources, rows_named)) or result
        ),
    )
    figures.figures_of_table(
        "smoke", tmp_path / "runs", tmp_path / "figs", progress=notes.append, rows_named=("LSTM A3C",)
    )
    assert named == [("cpu", jobs.Sources(), ("LSTM A3C",))]


def test_eval_video_writes_a_video_that_opencv_reads_back(capsys, tmp_path, floorplan1_tasks):
    """`eval --video FILE.mp4`: the recorded episodes as frames (the view and the target beside the
    map), one per start and per action; no .rrd needed; a name that is no .mp4 is one line."""
    import cv2

    from kgnavbench.cli import main

    video = tmp_path / "oracle.mp4"
    argv = ["eval", "--method", "oracle", "--kitchens", "FloorPlan1", "--episodes", "1"]
    argv += ["--runs", str(tmp_path / "runs"), "--record-episodes", "2"]
    assert main([*argv, "--video", str(video)]) == 0
    out = capsys.readouterr().out
    steps = int(re.search(r"recorded 2 episodes \((\d+) steps\)", out).group(1))
    capture = cv2.VideoCapture(str(video))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == steps + 2  # each episode's start, each action
    ok, frame = capture.read()
    assert ok and frame.shape == (480, 560, 3) and frame.std() > 10  # drawn, not blank
    assert not list(tmp_path.glob(".*partial*"))
    assert main([*argv, "--video", str(tmp_path / "oracle.avi")]) == 2
    assert "must end in .mp4" in capsys.readouterr().err


def test_max_steps_above_the_cap_records_to_the_cap(tmp_path):
    """A recording never runs past the evaluation's cap: FloorPlan25's first recorded episode is one of
    a seen target in a seen kitchen (cap 100), so max_steps=100,000 records 100 actions, Stop never
    drawn. (FloorPlan1's is an unseen target's, cap 1000: the same check, ten times longer.)"""
    path = tmp_path / "walk.rrd"
    out = record.record_episodes(
        "random_walk",
        {"stop_probability": "0"},
        path,
        kitchens=["FloorPlan25"],
        episodes=1,
        max_steps=100_000,
    )
    assert out["steps"] == 100


SLOW_WALKER = """
import time
DESCRIPTION = "turns, slowly"
class Policy:
    def reset(self, agent):
        pass
    def act(self, observations, infos):
        if len(observations) == 1:  # slow while recording (one episode at a time), not in the evaluation
            time.sleep(0.05)
        return {a: 4 for a in observations}
def make_policy(config, spec):
    return Policy()
"""


def test_a_recording_stopped_by_sigterm_leaves_no_partial_file(tmp_path, floorplan1_tasks):
    """SIGTERM (a `kill`, a batch system's limit) ends `eval --video --record` as Ctrl-C does: exit 130,
    and neither the video's nor the recording's partial file stays behind."""
    import os
    import signal
    import time

    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "slow_walker.py").write_text(SLOW_WALKER)
    argv = [sys.executable, "-m", "kgnavbench", "eval", "--method", "slow_walker", "--kitchens", "FloorPlan1"]
    argv += ["--episodes", "1", "--runs", "runs", "--record-episodes", "3", "--record-steps", "1000"]
    argv += ["--video", "walk.mp4", "--record", "walk.rrd"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    child = subprocess.Popen(
        argv, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob("*partial*")) and time.monotonic() < deadline and child.poll() is None:
        time.sleep(0.2)
    assert list(tmp_path.glob("*partial*")), "the recording never started"
    time.sleep(1.0)
    child.send_signal(signal.SIGTERM)
    _, err = child.communicate(timeout=60)
    assert child.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert not list(tmp_path.glob("*partial*")) and not (tmp_path / "walk.mp4").exists()


def _metrics(run_dir, lines):
    """A training run folder holding only a metrics.csv of (frames, val_sr, success_rate) lines."""
    run_dir.mkdir(parents=True)
    text = "frames,val_sr,success_rate\n" + "".join(
        f"{f},{'' if v is None else v},{'' if t is None else t}\n" for f, v, t in lines
    )
    (run_dir / "metrics.csv").write_text(text)
    return run_dir


def test_every_seeds_training_curves_and_their_mean(tmp_path, monkeypatch):
    """training_curves_seeds.png: each seed a thin line, the seeds' mean at their k-th points a thick
    one, in the row's colour; FF A3C's validation is named for its own kitchens; the CSV holds every
    point drawn; a row without runs is left out, and no run at all writes nothing."""
    a = _metrics(tmp_path / "a", [(1_000_100, None, 10.0), (2_500_300, 4.0, 20.0), (5_000_300, 8.0, 30.0)])
    b = _metrics(tmp_path / "b", [(1_000_500, None, 30.0), (2_500_700, 6.0, 40.0)])
    ff = _metrics(tmp_path / "ff", [(1_000_000, None, 5.0), (2_500_000, 1.0, 6.0)])
    assert figures.seeds_mean([([1.0, 2.0, 3.0], [4.0, 8.0, 9.0]), ([3.0, 4.0], [6.0, 10.0])]) == (
        [2.0, 3.0],
        [5.0, 9.0],
    )
    notes = []
    quoted = 'FF A3C, "own" kitchens'  # a name with a comma and quotes reads back whole
    rows = [("LSTM A3C", [a, b], True), (quoted, [ff], False), ("+KG", [], True)]
    png, csv_path = figures.seed_curves_figure(rows, tmp_path / "out", notes.append)
    assert png.name == "training_curves_seeds.png" and not notes
    width, height = figures.SEED_PANEL_SIZE
    assert _is_figure(png, (2 * width, height))
    with open(csv_path, newline="") as f:
        lines = list(csv.reader(f))
    assert lines[0] == ["row", "seed", "run", "frames", "column", "value"]
    assert ["LSTM A3C", "1", "b", "2500700", "val_sr", "6"] in lines
    assert [quoted, "0", "ff", "1000000", "success_rate", "5"] in lines
    assert len(lines) == 1 + (2 + 1 + 1) + (3 + 2 + 2)  # val_sr points, then success_rate points
    # the legends: one entry per row with its seed count; the seeds' own lines are unlabelled
    drawn, real = [], figures.curves_image
    monkeypatch.setattr(
        figures, "curves_image", lambda series, *a, **kw: drawn.append((series, kw)) or real(series, *a, **kw)
    )
    figures.seed_curves_figure(rows, tmp_path / "again", notes.append)
    validation, kw = drawn[0]
    assert list(validation) == [
        "LSTM A3C, 2 seeds #0", "LSTM A3C, 2 seeds #1", "LSTM A3C, 2 seeds",
        f"{quoted}, 1 seed" + figures.OWN_KITCHENS_NOTE,
    ]  # fmt: skip
    xs, ys = validation["LSTM A3C, 2 seeds"]  # the mean up to the shorter seed, in millions of frames
    assert xs == pytest.approx([2.5005]) and ys == [5.0]
    assert kw["thin"] == {"LSTM A3C, 2 seeds #0", "LSTM A3C, 2 seeds #1"}
    assert f"{quoted}, 1 seed" in drawn[1][0]  # its training episodes are the other rows' measure
    assert figures.seed_curves_figure([("+KG", [], True)], tmp_path / "none", notes.append) == []
    assert "skipped" in notes[-1] and not (tmp_path / "none").exists()
    with pytest.raises(FigureError, match="no such training run directory"):
        figures.seed_curves_figure([("LSTM A3C", [tmp_path / "gone"], True)], tmp_path / "x")


def test_the_curves_alone_come_from_the_zoos_runs_without_training(tmp_path):
    """`figures --curves-only --trained zoo`: the preset's runs found in zoo/ by their configs (as
    `table --trained` finds them), each seed's curve drawn, nothing trained or evaluated."""
    notes = []
    paths = figures.figures_of_table(
        "paper-protocol",
        tmp_path / "runs",
        tmp_path / "out",
        progress=notes.append,
        trained=Path("zoo"),
        rows_named=("LSTM A3C",),
        curves_only=True,
    )
    assert [p.name for p in paths] == ["training_curves_seeds.png", "training_curves_seeds.csv"]
    with open(paths[1], newline="") as f:
        runs = {line[2] for line in list(csv.reader(f))[1:]}
    assert runs == {"lstm_a3c-60ac5e8459", "lstm_a3c-4a4f223d5d", "lstm_a3c-6b53621d74"}
    assert not (tmp_path / "runs").exists()
    with pytest.raises(FigureError, match="--trained"):
        figures.figures_of_table("paper-protocol", tmp_path / "runs", tmp_path / "o", curves_only=True)
