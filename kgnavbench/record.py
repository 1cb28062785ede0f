"""Stage 34 — record: rerun-sdk recordings of episodes and training runs, and the viewer.

Episodes (`record_episodes`, a .rrd file), on two timelines: `step` counts actions over the whole
recording (so scrubbing plays the episodes one after another) and `episode` numbers the episode
every row belongs to. Episode e's start is logged at its own step, then one row per action:
  * `view`                 Image          the egocentric view (at the start, then after every action)
  * `target`               Image          the target image, once per episode
  * `map`                  EncodedImage   the top-down map (PNG) with the target outlined, the path so
                                          far and the agent, drawn with OpenCV; same rows as `view`
  * `episode`              TextDocument   kitchen, target, start and cap; again with the outcome
  * `action`               TextLog        the action name, level WARN when it failed (one per action)
  * `scalars/reward`, `scalars/return`, `scalars/collisions`, `scalars/failed`, `scalars/success`
                           Scalars        one row per action
  * `attention`            TextLog        the top-3 attended object types with their weights, and
  * `attention_weight/<Type>`  Scalars    each of them as a series: only for policies that have
                                          `explain(agent) -> {"attention": [(type, weight), ...]}`
Training (`record_training`): every column of a run's metrics.csv as `training/<group>/<column>`
Scalars on the timeline `frames` (agent steps).

A blueprint lays the views out (views and target on the left, the map in the middle, plots and logs
on the right). `view` opens the rerun viewer on a file, or says how to where there is no display.

The paper's figures (PNG, drawn with OpenCV) are `kgnavbench/figures.py`.

Nothing here is imported by the other stages: recording costs nothing when it is off.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from . import evaluate
from .env import parallel_env
from .errors import KgnavbenchError
from .files import symbolic_link
from .graph import MOVES
from .metrics import COLUMN_TITLES
from .plugins import PluginError, guarded, load_plugin
from .render import top_down_map
from .tasks import load_task_file, load_tasks
from .world import ACTIONS, move_offset

# the viewer keeps one layout per application id: episodes and training runs each get their own
EPISODES_APP, TRAINING_APP = "kgnavbench_episodes", "kgnavbench_training"
MAP_SIZE = 320  # px; ~40 kB a PNG frame, so a 1000-action episode makes a .rrd of ~30 MB
TOP_ATTENDED = 3
RRD_MAGIC = b"RRF"  # every .rrd file rerun 0.41 writes starts with "RRF2"


class RecordError(KgnavbenchError, ValueError):
    """Bad recording input: a missing or foreign .rrd file, an unreadable metrics.csv, bad data."""


# ------------------------------------------------------------------------------------------------
# Writing a recording


def _rrd_path(path) -> Path:
    path = Path(path)
    if path.suffix != ".rrd":
        raise RecordError(f"{path}: a recording's name must end in .rrd (the viewer goes by it)")
    return path


def _open_stream(
    path: Path, application_id: str, blueprint: rrb.Blueprint
) -> tuple[rr.RecordingStream, Path]:
    """A stream of its own (never the global one) saved into PATH.partial: the file appears under its
    name only once it is complete, so an interrupted recording never leaves a truncated .rrd."""
    path = _rrd_path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RecordError(f"cannot create {path.parent}: {e.strerror or e}") from e
    partial = path.with_name(path.name + ".partial")
    rec = rr.RecordingStream(application_id)
    # no wall-clock timelines: the file's timelines are exactly the ones we set
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    rec.save(partial)  # a file sink: no viewer is spawned
    # active, not only default: a viewer that shows an older layout of this application switches to it
    rec.send_blueprint(blueprint, make_active=True, make_default=True)
    return rec, partial


def _close_stream(rec: rr.RecordingStream, partial: Path, path: Path) -> None:
    rec.flush()
    rec.disconnect()  # closes the file and writes its footer
    os.replace(partial, path)


def _discard(rec: rr.RecordingStream, partial: Path) -> None:
    rec.disconnect()
    partial.unlink(missing_ok=True)


def _episode_blueprint(attention: bool) -> rrb.Blueprint:
    plots = [
        rrb.TimeSeriesView(
            name="reward, return, success, failed",
            origin="scalars",
            contents=["scalars/reward", "scalars/return", "scalars/success", "scalars/failed"],
        ),
        rrb.TimeSeriesView(name="collisions", origin="scalars", contents=["scalars/collisions"]),
    ]
    if attention:
        plots.append(rrb.TimeSeriesView(name="top-3 attention", origin="attention_weight"))
    logs = rrb.TextLogView(name="actions and attention", origin="/", contents=["action", "attention"])
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(name="egocentric view", origin="view"),
                rrb.Spatial2DView(name="target image", origin="target"),
            ),
            rrb.Vertical(
                rrb.Spatial2DView(name="top-down map", origin="map"),
                rrb.TextDocumentView(name="episode", origin="episode"),
                row_shares=[3, 1],
            ),
            rrb.Vertical(*plots, logs),
            column_shares=[1, 2, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="step", state="expanded"),
    )


def _episode_list(kitchens: list[str], episodes: int) -> list[tuple[str, int]]:
    """(kitchen, target row) for each recorded episode: the kitchens' targets in task-file order, taken
    in turn (the first target of every kitchen, then the second...)."""
    counts = {k: len(load_task_file()["kitchens"][k]["targets"]) for k in kitchens}
    chosen = []
    for row in range(max(counts.values())):
        chosen += [(k, row) for k in kitchens if row < counts[k]]
    if len(chosen) < episodes:
        raise RecordError(f"{', '.join(kitchens)} have only {len(chosen)} targets, not {episodes}")
    return chosen[:episodes]


def _attention(plugin, policy, agent: str) -> list[tuple[str, float]] | None:
    """The policy's top attended object types after its last act(), or None if it cannot tell."""
    explain = getattr(policy, "explain", None)
    if not callable(explain):
        return None
    answer = guarded(plugin, "explain()", explain, agent)
    try:
        return [(str(name), float(weight)) for name, weight in answer["attention"][:TOP_ATTENDED]]
    except (KeyError, TypeError, ValueError) as e:
        raise PluginError(
            f"{plugin.source}: explain() must return {{'attention': [(type, weight), ...]}}, got {answer!r}"
        ) from e


def _map_pixel(world, size: int):
    """World (x, z) in metres -> map pixel; the same transform as render.top_down_map draws with."""
    x0, z0, x1, z1 = world.kitchen.room
    margin = 0.2
    scale = (size - 1) / max(x1 - x0 + 2 * margin, z1 - z0 + 2 * margin)
    return lambda x, z: (int(round((x - x0 + margin) * scale)), int(round((z1 + margin - z) * scale)))


def _png(rgb: np.ndarray) -> bytes:
    """An RGB image as PNG bytes (flat colours: PNG is small and exact)."""
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RecordError("OpenCV could not encode the map as PNG")
    return png.tobytes()


def _map_image(graph, trail: list[int], target, bumps: list[tuple[int, int]], caption: str) -> np.ndarray:
    """The top-down map after the states of `trail` (RGB), with a caption strip above it. On top of
    render.top_down_map's path, agent and outlined target: the start (white dot), the destination
    (yellow ring) and each failed move (red cross at the obstacle side of the cell; `bumps` holds
    (state, action))."""
    poses = [graph.pose(s) for s in trail]
    rgb = top_down_map(graph.world, MAP_SIZE, [poses[-1]], poses, [target.object_index])
    px = _map_pixel(graph.world, MAP_SIZE)
    for s, a in bumps:
        p = graph.pose(s)
        dx, dz = move_offset(ACTIONS[a], p.heading)
        cx, cy = px(p.x + 0.1 * dx, p.z + 0.1 * dz)
        cv2.line(rgb, (cx - 3, cy - 3), (cx + 3, cy + 3), (230, 30, 30), 2, cv2.LINE_AA)
        cv2.line(rgb, (cx - 3, cy + 3), (cx + 3, cy - 3), (230, 30, 30), 2, cv2.LINE_AA)
    cv2.circle(rgb, px(poses[0].x, poses[0].z), 4, (255, 255, 255), -1, cv2.LINE_AA)
    cv2.circle(rgb, px(poses[0].x, poses[0].z), 4, (20, 20, 20), 1, cv2.LINE_AA)
    d = graph.pose(target.destination)
    cv2.circle(rgb, px(d.x, d.z), 7, (255, 220, 0), 2, cv2.LINE_AA)
    strip = np.full((18, MAP_SIZE, 3), 40, np.uint8)
    cv2.putText(strip, caption, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.vstack([strip, rgb])


class VideoSink:
    """Episodes as a video (OpenCV's VideoWriter, mp4v): per frame the egocentric view and the target
    image on the left, the top-down map with its caption (episode, step, action) on the right; a still
    title card between episodes is left out: the caption says which episode it is."""

    FPS = 4
    VIEW = 240  # px, the view and the target image each, scaled up from the env's views (nearest)

    def __init__(self, path: Path):
        self.path = Path(path)
        self.size = (self.VIEW + MAP_SIZE, max(2 * self.VIEW, MAP_SIZE + 18))
        self.partial = self.path.with_name(f".{self.path.stem}.partial{self.path.suffix}")
        self.writer = cv2.VideoWriter(str(self.partial), cv2.VideoWriter_fourcc(*"mp4v"), self.FPS, self.size)
        if not self.writer.isOpened():
            raise RecordError(f"OpenCV cannot write a video to {self.path} (mp4v)")

    def frame(self, view: np.ndarray, target: np.ndarray, map_rgb: np.ndarray) -> None:
        width, height = self.size
        canvas = np.full((height, width, 3), 30, np.uint8)
        for k, image in enumerate((view, target)):
            scaled = cv2.resize(image, (self.VIEW, self.VIEW), interpolation=cv2.INTER_NEAREST)
            canvas[k * self.VIEW : (k + 1) * self.VIEW, : self.VIEW] = scaled
        label = (8, self.VIEW + 20)
        cv2.putText(canvas, "target", label, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        canvas[: map_rgb.shape[0], self.VIEW : self.VIEW + map_rgb.shape[1]] = map_rgb
        self.writer.write(cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        self.writer.release()
        os.replace(self.partial, self.path)

    def discard(self) -> None:
        self.writer.release()
        self.partial.unlink(missing_ok=True)


def _policy_spec(config: evaluate.EvalConfig, seed: int, view_size: int, checkpoint):
    """The evaluation's PolicySpec; a checkpoint goes in it where the spec has a field for one."""
    spec = evaluate.policy_spec(config, seed, view_size)
    if checkpoint is not None:
        if "checkpoint" not in {f.name for f in dataclasses.fields(spec)}:
            raise RecordError("this kgnavbench's PolicySpec has no checkpoint field; cannot pass one")
        spec = dataclasses.replace(spec, checkpoint=str(checkpoint))
    return spec


def record_episodes(
    plugin_name: str,
    options: dict[str, str],
    path,
    kitchens: list[str] | None = None,
    episodes: int = 2,
    success_rule: str = "destination",
    seed: int = 0,
    checkpoint=None,
    max_steps: int | None = None,
    stop_ends: bool = True,
    run=None,
    video=None,
) -> dict:
    """Record `episodes` fixed episodes of method `plugin_name` into the .rrd file `path` and/or the
    video file `video` (.mp4: `VideoSink`).

    The policy is built as in an evaluation (same config, same PolicySpec and per-kitchen seed); the
    episodes are the task file's first fixed start of the kitchens' first targets (kitchens: default
    the first kitchen of Table I's split). Each episode runs to the evaluation's cap for its column, or
    to `max_steps` when given and smaller. A learned method's weights: `run` (a training run directory, whose
    best-validation checkpoint an evaluation would test) or `checkpoint` (a file; it wins).
    Returns {"path", "episodes", "steps", "successes", "collisions"}.
    """
    if path is None and video is None:
        raise RecordError("record_episodes needs a .rrd path, a video path, or both")
    path = _rrd_path(path) if path is not None else None  # before minutes of work, not after
    video = _video_path(video) if video is not None else None
    if not isinstance(episodes, int) or episodes < 1:
        raise RecordError(f"episodes must be a positive integer, not {episodes!r}")
    if max_steps is not None and (not isinstance(max_steps, int) or max_steps < 1):
        raise RecordError(f"max_steps must be a positive integer, not {max_steps!r}")
    kitchens = list(kitchens) if kitchens else evaluate.kitchens_of_split("table")[:1]
    fields = {
        "method": plugin_name,
        "options": tuple(sorted(options.items())),
        "success_rule": success_rule,
        "stop_ends": stop_ends,
        "kitchens": tuple(kitchens),
        "seed": seed,
    }
    if run and checkpoint is None:  # an explicit checkpoint wins over the run's selected one
        if "run" not in {f.name for f in dataclasses.fields(evaluate.EvalConfig)}:
            raise RecordError("this kgnavbench's evaluation takes no training run; pass checkpoint=")
        fields["run"] = str(run)
    # EvalConfig checks the rules and the kitchen names as an evaluation does; policy_spec reads its run
    config = evaluate.EvalConfig(**fields)
    plugin = load_plugin(plugin_name)
    plugin_config = plugin.config(dict(options))
    chosen = _episode_list(kitchens, episodes)

    rec, partial = None, None
    film = VideoSink(video) if video is not None else None
    totals = {"path": str(path or video), "episodes": 0, "steps": 0, "successes": 0, "collisions": 0}
    step = 0
    try:
        for kitchen in dict.fromkeys(k for k, _ in chosen):
            tasks = load_tasks(kitchen)
            graph = tasks.graph
            kitchen_seed = evaluate.kitchen_seed(seed, kitchen)
            spec = _policy_spec(config, kitchen_seed, graph.views.shape[1], checkpoint)
            policy = plugin.make_policy(plugin_config, spec)
            if rec is None and path is not None:  # the layout: whether the policy can explain itself
                explains = callable(getattr(policy, "explain", None))
                rec, partial = _open_stream(path, EPISODES_APP, _episode_blueprint(explains))
            env = parallel_env(
                kitchen=kitchen,
                n_agents=1,
                targets="all",
                success_rule=success_rule,
                stop_ends=stop_ends,
                tasks=tasks,
                features=True,  # as in evaluation
                privileged=True,  # the trail reads the states; the plugin sees them if PRIVILEGED
            )
            for row in (r for k, r in chosen if k == kitchen):
                e = totals["episodes"]
                step, info = _record_episode(
                    rec or _NO_RECORDING, plugin, policy, env, tasks, row, e, step, max_steps, film
                )
                totals["episodes"] += 1
                totals["steps"] += info["episode_length"]
                totals["successes"] += int(info["success"])
                totals["collisions"] += info["collisions"]
        if rec is not None:
            _close_stream(rec, partial, path)
        if film is not None:
            film.close()
    except BaseException:
        if rec is not None:
            _discard(rec, partial)
        if film is not None:
            film.discard()
        raise
    return totals


class _NoRecording:
    """A rerun recording stream that records nothing (a video alone was asked for)."""

    def set_time(self, *args, **kwargs) -> None:
        pass

    def log(self, *args, **kwargs) -> None:
        pass


_NO_RECORDING = _NoRecording()


def _video_path(path) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise RecordError(f"{path}: a video file must end in .mp4")
    return path


def _record_episode(rec, plugin, policy, env, tasks, row: int, e: int, step: int, max_steps, film=None):
    """Run and log one episode from global step `step`: its start there, each action one step later;
    with `film` (a VideoSink) one video frame per row too. Returns the next free step and the
    episode's last info."""
    graph = tasks.graph
    target = tasks.targets[row]
    column = evaluate.column_of(tasks.split, target.seen)
    # never past the evaluation's cap: an episode ends there whatever max_steps says
    cap = min(max_steps or evaluate.UNSEEN_CAP, evaluate.episode_cap(column))
    start = target.starts[0]
    observations, infos = env.reset(
        options={"episodes": [{"target": target.object_id, "start": start, "max_steps": cap}]}
    )
    (agent,) = env.agents
    guarded(plugin, "reset()", policy.reset, agent)
    header = (
        f"## Episode {e}: {tasks.kitchen}, {target.type}\n\n"
        f"* target `{target.object_id}` ({target.kind}, {'seen' if target.seen else 'unseen'}; "
        f"column *{COLUMN_TITLES[column]}*)\n"
        f"* start state {start}, shortest path {infos[agent]['shortest_path']} actions, cap {cap}\n"
    )
    trail, bumps = [start], []

    def at(s: int) -> None:
        rec.set_time("step", sequence=s)
        rec.set_time("episode", sequence=e)

    def show(caption: str) -> None:  # the view and the map after the trail so far
        image = _map_image(graph, trail, target, bumps, caption)
        rec.log("view", rr.Image(observations[agent]["view"]))
        if rec is not _NO_RECORDING:
            rec.log("map", rr.EncodedImage(contents=_png(image), media_type="image/png"))
        if film is not None:
            film.frame(observations[agent]["view"], observations[agent]["target"], image)

    at(step)
    rec.log("episode", rr.TextDocument(header, media_type=rr.MediaType.MARKDOWN))
    rec.log("target", rr.Image(observations[agent]["target"]))
    show(f"episode {e} start")
    total_return = 0.0
    info = infos[agent]
    while env.agents:
        shown = infos if plugin.privileged else evaluate.without_privileged(infos)
        actions = guarded(plugin, "act()", policy.act, observations, shown)
        evaluate.check_actions(plugin, actions, env.agents)
        attended = _attention(plugin, policy, agent)
        before = trail[-1]
        a = int(actions[agent])
        observations, rewards, terminations, truncations, infos = env.step(actions)
        info = infos[agent]
        trail.append(info["state"])
        # a failed action: a move into an obstacle (a collision) or an OpenObject with nothing to open
        failed = not bool(graph.ok[before, a])
        if failed and a in MOVES:
            bumps.append((before, a))
        total_return += rewards[agent]
        step += 1
        at(step)
        name = ACTIONS[a] + (
            " (failed: collision)" if failed and a in MOVES else " (failed)" if failed else ""
        )
        rec.log("action", rr.TextLog(name, level="WARN" if failed else "INFO"))
        show(f"ep {e} step {info['episode_length']}: {name}  collisions {info['collisions']}")
        rec.log("scalars/reward", rr.Scalars(rewards[agent]))
        rec.log("scalars/return", rr.Scalars(total_return))
        rec.log("scalars/collisions", rr.Scalars(info["collisions"]))
        rec.log("scalars/failed", rr.Scalars(float(failed)))
        rec.log("scalars/success", rr.Scalars(float(info["success"])))
        if attended is not None:
            text = ", ".join(f"{t} {w:.2f}" for t, w in attended)
            rec.log("attention", rr.TextLog(f"top-{TOP_ATTENDED}: {text}" if attended else "nothing visible"))
            for t, w in attended:
                rec.log(f"attention_weight/{rr.escape_entity_path_part(t)}", rr.Scalars(w))
        if terminations[agent] or truncations[agent]:
            break
    outcome = (
        f"\n**{'success' if info['success'] else 'failure'}** after {info['episode_length']} actions "
        f"({'Stop' if terminations[agent] else 'the cap'}); path {info['path_length']}, "
        f"{info['collisions']} collisions, last view shows the target: {info['last_view_shows_target']}\n"
    )
    rec.log("episode", rr.TextDocument(header + outcome, media_type=rr.MediaType.MARKDOWN))
    return step + 1, info


# ------------------------------------------------------------------------------------------------
# Training curves

# metrics.csv columns (train stage) -> the plot they share; an unknown column gets "other"
TRAINING_GROUPS = {
    "mean_reward": "reward",
    "mean_return": "reward",
    "success_rate": "success",
    "val_sr": "validation",
    "val_spl": "validation",
    "rl_loss": "loss",
    "il_loss": "loss",
    "tse_loss": "loss",
    "frames_per_s": "throughput",
    "seconds": "progress",
    "updates": "progress",
    "episodes": "progress",
}


def read_metrics(metrics_csv) -> dict[str, tuple[list[int], list[float]]]:
    """{column: (frames, values)} of a metrics.csv, leaving out empty cells (a value not measured at that
    row, e.g. validation between checkpoints)."""
    metrics_csv = Path(metrics_csv)
    if symbolic_link(metrics_csv):
        raise RecordError(symbolic_link(metrics_csv))
    try:
        with metrics_csv.open(newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise RecordError(f"cannot read {metrics_csv}: {e}") from e
    if "frames" not in columns:
        raise RecordError(f"{metrics_csv} has no 'frames' column (columns: {', '.join(columns) or 'none'})")
    series: dict[str, tuple[list[int], list[float]]] = {c: ([], []) for c in columns if c != "frames"}
    for n, row in enumerate(rows, start=2):  # line 1 is the header
        try:
            frames = int(float(row["frames"]))
            for c, (xs, ys) in series.items():
                cell = (row.get(c) or "").strip()
                if cell:
                    ys.append(float(cell))
                    xs.append(frames)
        except (TypeError, ValueError) as e:
            raise RecordError(f"{metrics_csv}, line {n}: not a number ({e})") from e
    return series


def record_training(metrics_csv, path) -> dict:
    """Log a training run's metrics.csv into the .rrd file `path`: one Scalars series per column, at
    `training/<group>/<column>` on the timeline `frames`. Returns {"path", "rows", "series"}."""
    path = _rrd_path(path)
    series = {c: xy for c, xy in read_metrics(metrics_csv).items() if xy[0]}
    if not series:
        raise RecordError(f"{metrics_csv} holds no values to record")
    groups: dict[str, list[str]] = {}
    for c in series:
        groups.setdefault(TRAINING_GROUPS.get(c, "other"), []).append(c)
    views = [rrb.TimeSeriesView(name=g, origin=f"training/{g}") for g in groups]
    blueprint = rrb.Blueprint(
        rrb.Grid(*views),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="frames"),
    )
    rec, partial = _open_stream(path, TRAINING_APP, blueprint)
    try:
        for c, (xs, ys) in series.items():
            # a whole column at once: one chunk per series instead of one log call per cell
            rec.send_columns(
                f"training/{TRAINING_GROUPS.get(c, 'other')}/{rr.escape_entity_path_part(c)}",
                indexes=[rr.TimeColumn("frames", sequence=xs)],
                columns=rr.Scalars.columns(scalars=ys),
            )
        _close_stream(rec, partial, path)
    except BaseException:
        _discard(rec, partial)
        raise
    rows = len({x for xs, _ in series.values() for x in xs})
    return {"path": str(path), "rows": rows, "series": {c: len(xs) for c, (xs, _) in series.items()}}


# ------------------------------------------------------------------------------------------------
# Viewing


def has_display() -> bool:
    """Whether a native viewer window can open here: macOS and Windows always; elsewhere an X or
    Wayland display must be set."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def rerun_command() -> list[str]:
    """The viewer shipped with the rerun-sdk wheel: the `rerun` next to this Python (a venv's bin),
    else on PATH, else `python -m rerun`."""
    name = "rerun.exe" if sys.platform == "win32" else "rerun"
    beside = Path(sys.executable).parent / name
    if beside.is_file():
        return [str(beside)]
    found = shutil.which("rerun")
    return [found] if found else [sys.executable, "-m", "rerun"]


def check_recording(path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise RecordError(
            f"{path}: no such recording; make one with `kgnavbench eval ... --record {path.name}`"
        )
    try:
        with path.open("rb") as f:
            magic = f.read(len(RRD_MAGIC))
    except OSError as e:
        raise RecordError(f"cannot read {path}: {e.strerror or e}") from e
    if magic != RRD_MAGIC:
        raise RecordError(f"{path} is not a rerun recording (.rrd)")
    return path


def view(path) -> int:
    """Open the rerun viewer on a recording and wait for it to close; its exit status. Where there is
    no display, print how to watch the file instead and return 0."""
    path = check_recording(path)
    command = rerun_command()
    if has_display():
        return subprocess.run([*command, str(path)], check=False).returncode
    here = " ".join(command)
    print(
        "kgnavbench: no display here (DISPLAY and WAYLAND_DISPLAY are unset), so no viewer was opened.\n"
        f"To watch {path}:\n"
        f"  * copy it to a machine with a display and run: rerun {path.name}\n"
        "    (the viewer comes with `pip install rerun-sdk==0.41.0`)\n"
        f"  * or serve the web viewer from here: {here} --serve-web --bind 127.0.0.1 {path}\n"
        "    and open http://127.0.0.1:9090 in a browser on this machine; from another machine, forward\n"
        "    both ports first: ssh -L 9090:127.0.0.1:9090 -L 9876:127.0.0.1:9876 THIS_HOST"
    )
    return 0
