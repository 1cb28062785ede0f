"""Stage 10 — record: rerun-sdk recordings of episodes and training runs, and the paper's figures.

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

Figures (PNG, OpenCV only): `bar_line_figure` (bars with a line on a second axis), `scatter_figure`
(labelled points, e.g. a t-SNE), `curves_figure` (training curves); `tsne` is exact t-SNE in torch.
`figures` draws the paper's figures from the table's runs (collisions and last-view rate on unseen
kitchens, the t-SNE of the GCN's node features, training curves); `figures_of_table` from a preset.

Nothing here is imported by the other stages: recording costs nothing when it is off.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from . import evaluate
from .env import parallel_env
from .kitchens import KITCHEN_NAMES
from .plugins import PluginError, guarded, load_plugin
from .render import top_down_map, type_colour
from .tasks import MOVES, load_task_file, load_tasks
from .world import ACTIONS, move_offset

# the viewer keeps one layout per application id: episodes and training runs each get their own
EPISODES_APP, TRAINING_APP = "kgnavbench_episodes", "kgnavbench_training"
MAP_SIZE = 320  # px; ~40 kB a PNG frame, so a 1000-action episode makes a .rrd of ~30 MB
TOP_ATTENDED = 3
RRD_MAGIC = b"RRF"  # every .rrd file rerun 0.41 writes starts with "RRF2"


class RecordError(ValueError):
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


def _map_frame(graph, trail: list[int], target, bumps: list[tuple[int, int]], caption: str) -> bytes:
    """The top-down map after the states of `trail` as PNG bytes (flat colours: PNG is small and exact),
    with a caption strip above it. On top of render.top_down_map's path, agent and outlined target: the
    start (white dot), the destination (yellow ring) and each failed move (red cross at the obstacle
    side of the cell; `bumps` holds (state, action))."""
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
    ok, png = cv2.imencode(".png", cv2.cvtColor(np.vstack([strip, rgb]), cv2.COLOR_RGB2BGR))
    if not ok:
        raise RecordError("OpenCV could not encode the map as PNG")
    return png.tobytes()


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
) -> dict:
    """Record `episodes` fixed episodes of method `plugin_name` into the .rrd file `path`.

    The policy is built as in an evaluation (same config, same PolicySpec and per-kitchen seed); the
    episodes are the task file's first fixed start of the kitchens' first targets (kitchens: default
    the first kitchen of Table I's split). Each episode runs to the evaluation's cap for its column, or
    to `max_steps` when given. A learned method's weights: `run` (a training run directory, whose
    best-validation checkpoint an evaluation would test) or `checkpoint` (a file; it wins).
    Returns {"path", "episodes", "steps", "successes", "collisions"}.
    """
    path = _rrd_path(path)  # before minutes of work, not after
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
    totals = {"path": str(path), "episodes": 0, "steps": 0, "successes": 0, "collisions": 0}
    step = 0
    try:
        for kitchen in dict.fromkeys(k for k, _ in chosen):
            tasks = load_tasks(kitchen)
            graph = tasks.graph
            kitchen_seed = seed * 1000 + KITCHEN_NAMES.index(kitchen)  # evaluate_kitchen's seed
            spec = _policy_spec(config, kitchen_seed, graph.views.shape[1], checkpoint)
            policy = plugin.make_policy(plugin_config, spec)
            if rec is None:  # the layout depends on whether the policy can explain itself
                explains = callable(getattr(policy, "explain", None))
                rec, partial = _open_stream(path, EPISODES_APP, _episode_blueprint(explains))
            env = parallel_env(
                kitchen=kitchen,
                n_agents=1,
                targets="all",
                success_rule=success_rule,
                stop_ends=stop_ends,
                tasks=tasks,
            )
            for row in (r for k, r in chosen if k == kitchen):
                e = totals["episodes"]
                step, info = _record_episode(rec, plugin, policy, env, tasks, row, e, step, max_steps)
                totals["episodes"] += 1
                totals["steps"] += info["episode_length"]
                totals["successes"] += int(info["success"])
                totals["collisions"] += info["collisions"]
        _close_stream(rec, partial, path)
    except BaseException:
        if rec is not None:
            _discard(rec, partial)
        raise
    return totals


def _record_episode(rec, plugin, policy, env, tasks, row: int, e: int, step: int, max_steps):
    """Run and log one episode from global step `step`: its start there, each action one step later.
    Returns the next free step and the episode's last info."""
    graph = tasks.graph
    target = tasks.targets[row]
    column = evaluate.column_of(tasks.split, target.seen)
    cap = max_steps if max_steps is not None else evaluate.episode_cap(column)
    start = target.starts[0]
    observations, infos = env.reset(
        options={"episodes": [{"target": target.object_id, "start": start, "max_steps": cap}]}
    )
    (agent,) = env.agents
    guarded(plugin, "reset()", policy.reset, agent)
    header = (
        f"## Episode {e}: {tasks.kitchen}, {target.type}\n\n"
        f"* target `{target.object_id}` ({target.kind}, {'seen' if target.seen else 'unseen'}; "
        f"column *{evaluate.COLUMN_TITLES[column]}*)\n"
        f"* start state {start}, shortest path {infos[agent]['shortest_path']} actions, cap {cap}\n"
    )
    trail, bumps = [start], []

    def at(s: int) -> None:
        rec.set_time("step", sequence=s)
        rec.set_time("episode", sequence=e)

    at(step)
    rec.log("episode", rr.TextDocument(header, media_type=rr.MediaType.MARKDOWN))
    rec.log("target", rr.Image(observations[agent]["target"]))
    rec.log("view", rr.Image(observations[agent]["view"]))
    rec.log(
        "map",
        rr.EncodedImage(
            contents=_map_frame(graph, trail, target, bumps, f"episode {e} start"),
            media_type="image/png",
        ),
    )
    total_return = 0.0
    info = infos[agent]
    while env.agents:
        shown = infos if plugin.privileged else evaluate._without_expert(infos)
        actions = guarded(plugin, "act()", policy.act, observations, shown)
        evaluate._check_actions(plugin, actions, env.agents)
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
        rec.log("view", rr.Image(observations[agent]["view"]))
        caption = f"ep {e} step {info['episode_length']}: {name}  collisions {info['collisions']}"
        rec.log(
            "map",
            rr.EncodedImage(
                contents=_map_frame(graph, trail, target, bumps, caption), media_type="image/png"
            ),
        )
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


# ------------------------------------------------------------------------------------------------
# t-SNE (van der Maaten & Hinton 2008), exact: O(n^2) memory, meant for the 125 GCN node features


def _conditional_p(d: torch.Tensor, perplexity: float, steps: int = 100) -> torch.Tensor:
    """P(j|i) with each row's Gaussian precision beta found by bisection so that its entropy is
    log(perplexity); all rows at once."""
    n = len(d)
    off = ~torch.eye(n, dtype=torch.bool)
    # shifting a row's distances by its nearest neighbour's leaves P(j|i) unchanged and keeps exp finite
    d = (d - d.masked_fill(~off, math.inf).min(1, keepdim=True).values).masked_fill(~off, 0.0)
    target = math.log(perplexity)
    beta = torch.ones(n, 1, dtype=d.dtype)
    lo = torch.zeros_like(beta)
    hi = torch.full_like(beta, math.inf)
    for _ in range(steps):
        p = torch.exp(-d * beta) * off
        total = p.sum(1, keepdim=True)
        entropy = torch.log(total) + beta * (d * p).sum(1, keepdim=True) / total
        too_wide = entropy > target  # too many neighbours: narrow the Gaussian (raise beta)
        lo = torch.where(too_wide, beta, lo)
        hi = torch.where(too_wide, hi, beta)
        beta = torch.where(torch.isinf(hi), beta * 2, (lo + hi) / 2)
    p = torch.exp(-d * beta) * off
    return p / p.sum(1, keepdim=True)


def tsne(
    x: torch.Tensor, dims: int = 2, perplexity: float = 30.0, iterations: int = 1000, seed: int = 0
) -> torch.Tensor:
    """Embed the rows of x (n, d) in `dims` dimensions. Gradient descent with momentum (0.5, then 0.8)
    and per-parameter gains, early exaggeration 12 over the first quarter (at most 250 iterations), the
    learning rate scikit-learn's "auto" picks. float64 on the CPU: the same seed gives the same result."""
    if x.ndim != 2 or len(x) < 3:
        raise ValueError(f"t-SNE needs a (n, d) matrix with n >= 3, not shape {tuple(x.shape)}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # (n, n) with n ~ 100: handing work to threads costs far more than it saves
    try:
        y = _tsne(x.detach().to("cpu", torch.float64), dims, perplexity, iterations, seed)
    finally:
        torch.set_num_threads(threads)
    return y.to(torch.float32)


def _tsne(x: torch.Tensor, dims: int, perplexity: float, iterations: int, seed: int) -> torch.Tensor:
    """tsne's body on a float64 CPU tensor."""
    n = len(x)
    perplexity = min(float(perplexity), (n - 1) / 3)  # more neighbours than points cannot be matched
    p = _conditional_p(torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist").square(), perplexity)
    p = ((p + p.T) / (2 * n)).clamp_min(1e-12)  # symmetric joint probabilities
    exaggeration, early = 12.0, min(250, iterations // 4)
    rate = max(n / exaggeration / 4, 50.0)
    generator = torch.Generator().manual_seed(seed)
    y = torch.randn(n, dims, generator=generator, dtype=torch.float64) * 1e-2  # N(0, 1e-4 I) as in the paper
    velocity = torch.zeros_like(y)
    gains = torch.ones_like(y)
    for it in range(iterations):
        num = 1.0 / (1.0 + (y[:, None] - y[None]).square().sum(-1))  # Student-t kernel of the embedding
        num.fill_diagonal_(0.0)
        q = (num / num.sum()).clamp_min(1e-12)
        w = ((exaggeration if it < early else 1.0) * p - q) * num
        grad = 4.0 * (w.sum(1, keepdim=True) * y - w @ y)
        # delta-bar-delta gains: a larger step where the last move still goes downhill, smaller elsewhere
        gains = torch.where((grad > 0) != (velocity > 0), gains + 0.2, gains * 0.8).clamp_min(0.01)
        velocity = (0.5 if it < early else 0.8) * velocity - rate * gains * grad
        y = y + velocity
        y = y - y.mean(0)
    return y


# ------------------------------------------------------------------------------------------------
# Figures: PNG with OpenCV, white background, axes with round ticks

FIGURE_SIZE = (1000, 600)  # width, height in pixels
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (30, 30, 30)
GRID = (225, 225, 225)
# BGR: tab10's blue, orange, green, red, purple, brown, pink, grey, olive, cyan
PALETTE = (
    (180, 119, 31),
    (14, 127, 255),
    (44, 160, 44),
    (40, 39, 214),
    (189, 103, 148),
    (75, 86, 140),
    (194, 119, 227),
    (127, 127, 127),
    (34, 189, 188),
    (207, 190, 23),
)


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """Round tick values covering [lo, hi] in about n steps (1, 2, 2.5 or 5 times a power of ten)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * (1 - 1e-9))
    first = math.floor(lo / step + 1e-9) * step
    count = math.ceil((hi - first) / step - 1e-9)
    return [first + i * step for i in range(count + 1)]


def _fmt(v: float) -> str:
    """A tick label: 1500000 -> 1.5M, 20000 -> 20k, 0.30000000000000004 -> 0.3."""
    for limit, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= limit:
            return f"{round(v / limit, 3):g}{suffix}"
    return f"{round(v, 6):g}"


def _text(img, text: str, org, scale=0.5, colour=INK, thickness=1, align="left", valign="baseline"):
    """putText with horizontal (left/centre/right) and vertical (top/middle/baseline) alignment."""
    (w, h), _ = cv2.getTextSize(text, FONT, scale, thickness)
    x, y = org
    x -= {"left": 0, "centre": w // 2, "right": w}[align]
    y += {"top": h, "middle": h // 2, "baseline": 0}[valign]
    cv2.putText(img, text, (int(x), int(y)), FONT, scale, colour, thickness, cv2.LINE_AA)
    return w, h


def _vertical_text(img, text: str, centre, scale=0.55, colour=INK) -> None:
    """Text read bottom to top (a y-axis label): drawn on its own strip, rotated, pasted."""
    (w, h), base = cv2.getTextSize(text, FONT, scale, 1)
    strip = np.full((h + base + 4, w + 4, 3), 255, np.uint8)
    cv2.putText(strip, text, (2, h + 2), FONT, scale, colour, 1, cv2.LINE_AA)
    strip = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
    sh, sw = strip.shape[:2]
    x0, y0 = int(centre[0] - sw / 2), int(centre[1] - sh / 2)
    x0, y0 = max(x0, 0), max(y0, 0)
    region = img[y0 : y0 + sh, x0 : x0 + sw]
    np.minimum(region, strip[: region.shape[0], : region.shape[1]], out=region)


def _wrap(text: str, width: int, scale: float) -> list[str]:
    """Words of `text` in lines no wider than `width` pixels (a long word gets a line of its own)."""
    lines: list[str] = []
    for word in text.split():
        trial = f"{lines[-1]} {word}" if lines else word
        if lines and cv2.getTextSize(trial, FONT, scale, 1)[0][0] <= width:
            lines[-1] = trial
        else:
            lines.append(word)
    return lines or [""]


class _Axes:
    """A plot area inside margins, mapping data to pixels; y ticks on the left (and optionally right)."""

    def __init__(self, img, left, top, right, bottom, xlim, ylim):
        self.img, self.left, self.top, self.right, self.bottom = img, left, top, right, bottom
        self.xlim, self.ylim = xlim, ylim

    def px(self, x: float, y: float, ylim=None) -> tuple[int, int]:
        (x0, x1), (y0, y1) = self.xlim, ylim or self.ylim
        u = self.left + (x - x0) / ((x1 - x0) or 1) * (self.right - self.left)
        v = self.bottom - (y - y0) / ((y1 - y0) or 1) * (self.bottom - self.top)
        return int(round(u)), int(round(v))

    def y_axis(self, ticks, label: str, side: str = "left", colour=INK, grid: bool = True) -> None:
        x = self.left if side == "left" else self.right
        ylim = (ticks[0], ticks[-1])
        for t in ticks:
            _, y = self.px(0, t, ylim)
            if grid:
                cv2.line(self.img, (self.left, y), (self.right, y), GRID, 1)
            cv2.line(
                self.img, (x - 5 if side == "left" else x, y), (x if side == "left" else x + 5, y), colour, 1
            )
            offset = -9 if side == "left" else 9
            _text(
                self.img,
                _fmt(t),
                (x + offset, y),
                0.45,
                colour,
                align="right" if side == "left" else "left",
                valign="middle",
            )
        widest = max(cv2.getTextSize(_fmt(t), FONT, 0.45, 1)[0][0] for t in ticks)
        lx = x - widest - 28 if side == "left" else x + widest + 28
        _vertical_text(self.img, label, (lx, (self.top + self.bottom) / 2), 0.55, colour)

    def x_ticks(self, ticks, label: str) -> None:
        for t in ticks:
            x, _ = self.px(t, self.ylim[0])
            cv2.line(self.img, (x, self.top), (x, self.bottom), GRID, 1)
            cv2.line(self.img, (x, self.bottom), (x, self.bottom + 5), INK, 1)
            _text(self.img, _fmt(t), (x, self.bottom + 10), 0.45, align="centre", valign="top")
        _text(self.img, label, ((self.left + self.right) // 2, self.bottom + 48), 0.55, align="centre")

    def frame(self) -> None:
        cv2.rectangle(self.img, (self.left, self.top), (self.right, self.bottom), INK, 1)


def _canvas(title: str, size) -> np.ndarray:
    width, height = size
    img = np.full((height, width, 3), 255, np.uint8)
    _text(img, title, (width // 2, 30), 0.75, INK, 2, align="centre")
    return img


def _legend(img, entries: list[tuple[str, tuple, str]], right: int, top: int) -> None:
    """Entries (label, colour, "bar" | "line") in a row ending at x=right, at height top."""
    x = right
    for label, colour, kind in reversed(entries):
        w = cv2.getTextSize(label, FONT, 0.5, 1)[0][0]
        x -= w
        _text(img, label, (x, top), 0.5, valign="middle")
        x -= 30
        if kind == "bar":
            cv2.rectangle(img, (x, top - 7), (x + 22, top + 7), colour, -1)
        else:
            cv2.line(img, (x, top), (x + 22, top), colour, 2, cv2.LINE_AA)
            cv2.circle(img, (x + 11, top), 4, colour, -1, cv2.LINE_AA)
        x -= 24


def _write_png(path, img: np.ndarray) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise RecordError(f"cannot create {path.parent}: {e.strerror or e}") from e
    if not cv2.imwrite(str(path), img):
        raise RecordError(f"could not write {path} (OpenCV writes .png, .jpg and a few more)")
    return path


def bar_line_figure(
    labels: list[str],
    bars: list[float],
    line: list[float],
    path,
    title: str,
    bar_label: str,
    line_label: str,
    size=FIGURE_SIZE,
) -> Path:
    """Bars (left axis) and a line with markers (right axis), one slot per label; the paper's figure of
    collisions per episode (bars) and the last-view-shows-target rate (line) per method. Each slot's
    values are written under its label in the colours of their series. A NaN value draws nothing."""
    if not labels or not len(labels) == len(bars) == len(line):
        raise RecordError(f"{len(labels)} labels, {len(bars)} bars and {len(line)} line values must match")
    img = _canvas(title, size)
    width, height = size
    finite = [v for v in bars if math.isfinite(v)] or [1.0]
    bar_ticks = _ticks(0.0, max(max(finite), 0.0) * 1.05)
    finite = [v for v in line if math.isfinite(v)] or [1.0]
    line_ticks = _ticks(min(0.0, min(finite)), max(finite) * 1.05)
    ax = _Axes(img, 100, 80, width - 100, height - 110, (0, len(labels)), (bar_ticks[0], bar_ticks[-1]))
    line_colour = PALETTE[1]
    ax.y_axis(bar_ticks, bar_label, "left")
    ax.y_axis(line_ticks, line_label, "right", line_colour, grid=False)
    slot = (ax.right - ax.left) / len(labels)
    points, values = [], []
    for i, (label, b, v) in enumerate(zip(labels, bars, line)):
        cx = int(ax.left + (i + 0.5) * slot)
        if math.isfinite(b):
            _, top = ax.px(0, b)
            half = int(slot * 0.3)
            cv2.rectangle(img, (cx - half, top), (cx + half, ax.bottom), PALETTE[0], -1)
        if math.isfinite(v):
            points.append((cx, ax.px(0, v, (line_ticks[0], line_ticks[-1]))[1]))
        names = _wrap(label, int(slot) - 6, 0.45)[:3]
        for k, text in enumerate(names):
            _text(img, text, (cx, ax.bottom + 10 + 18 * k), 0.45, align="centre", valign="top")
        values.append((cx, ax.bottom + 14 + 18 * len(names), b, v))
    if len(points) > 1:
        cv2.polylines(img, [np.array(points, np.int32)], False, line_colour, 2, cv2.LINE_AA)
    for p in points:
        cv2.circle(img, p, 5, line_colour, -1, cv2.LINE_AA)
    # the values under each slot's name, in their series' colours: labels in the plot would collide
    # with the line and the bars wherever the two are close
    for cx, y, b, v in values:
        for k, (value, colour) in enumerate(((b, PALETTE[0]), (v, line_colour))):
            if math.isfinite(value):
                _text(
                    img,
                    f"{value:.2f}" if k == 0 else f"{value:.1f}",
                    (cx, y + 17 * k),
                    0.45,
                    colour,
                    align="centre",
                    valign="top",
                )
    ax.frame()
    _legend(img, [(bar_label, PALETTE[0], "bar"), (line_label, line_colour, "line")], width - 100, 58)
    return _write_png(path, img)


def _overlaps(box, boxes) -> bool:
    return any(box[0] < o[2] and o[0] < box[2] and box[1] < o[3] and o[1] < box[3] for o in boxes)


def _place_label(label: str, p, placed, width: int, height: int):
    """A box for `label` near point p that overlaps no box in `placed`: beside the point first, then in
    eight directions further out; (box, anchor) with anchor the end of a leader line, or None. Where no
    place is free, the label goes right of its point anyway."""
    (w, h), _ = cv2.getTextSize(label, FONT, 0.38, 1)
    candidates = [((p[0] + 8, p[1] - h // 2), None), ((p[0] - 8 - w, p[1] - h // 2), None)]
    for r in (16, 28, 42):
        for dx, dy in ((1, -1), (-1, -1), (1, 1), (-1, 1), (0, -1), (0, 1), (1, 0), (-1, 0)):
            ax, ay = p[0] + dx * r, p[1] + dy * r
            x = ax if dx > 0 else ax - w if dx < 0 else ax - w // 2
            y = ay - h if dy < 0 else ay if dy > 0 else ay - h // 2
            candidates.append(((x, y), (ax, ay)))
    for (x, y), anchor in candidates:
        box = (x, y, x + w, y + h + 2)
        inside = box[0] >= 0 and box[1] >= 40 and box[2] < width and box[3] < height
        if inside and not _overlaps(box, placed):
            return box, anchor
    (x, y), _ = candidates[0]
    return (x, y, x + w, y + h + 2), None


def scatter_figure(points, labels: list[str], path, title: str, size=FIGURE_SIZE) -> Path:
    """Points (n, 2) each with its label written beside it (a t-SNE of object types: the coordinates
    have no units, so no ticks). Labels keep clear of the other labels and points where they can (see
    _place_label)."""
    pts = np.asarray(points.detach().cpu() if isinstance(points, torch.Tensor) else points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) != len(labels) or not len(pts):
        raise RecordError(
            f"scatter_figure needs (n, 2) points and n labels, not {pts.shape} and {len(labels)}"
        )
    img = _canvas(title, size)
    width, height = size
    lo, hi = pts.min(0), pts.max(0)
    pad = (hi - lo) * 0.08 + 1e-9  # room for the labels of the outermost points
    ax = _Axes(
        img,
        40,
        60,
        width - 40,
        height - 30,
        (lo[0] - pad[0], hi[0] + pad[0]),
        (lo[1] - pad[1], hi[1] + pad[1]),
    )
    ax.frame()
    pixels = [ax.px(x, y) for x, y in pts]
    placed = [(x - 6, y - 6, x + 6, y + 6) for x, y in pixels]  # labels must not hide the points either
    for p, label in zip(pixels, labels):
        rgb = type_colour(label)  # object types keep the colours they have in the renders
        cv2.circle(img, p, 5, (rgb[2], rgb[1], rgb[0]), -1, cv2.LINE_AA)
        cv2.circle(img, p, 5, INK, 1, cv2.LINE_AA)
    for p, label in zip(pixels, labels):
        box, anchor = _place_label(label, p, placed, width, height)
        placed.append(box)
        if anchor is not None:  # a label moved away from its point gets a leader line
            cv2.line(img, p, anchor, (170, 170, 170), 1, cv2.LINE_AA)
        _text(img, label, (box[0], box[3] - 2), 0.38, (70, 70, 70))
    return _write_png(path, img)


def curves_figure(
    series: dict[str, tuple[list[float], list[float]]],
    path,
    title: str,
    xlabel: str,
    ylabel: str,
    size=FIGURE_SIZE,
    x_include: tuple[float, ...] = (),
    y_include: tuple[float, ...] = (),
) -> Path:
    """One line per named series (xs, ys) on shared axes, with a legend; NaN values break a line. The
    axes cover the data and the values of x_include and y_include (0: curves over frames from the start,
    a rate from zero)."""
    clean = {}
    for name, (xs, ys) in series.items():
        xs, ys = list(map(float, xs)), list(map(float, ys))
        if len(xs) != len(ys):
            raise RecordError(f"series {name!r}: {len(xs)} x values but {len(ys)} y values")
        clean[name] = (xs, ys)
    xs_all = [x for xs, _ in clean.values() for x in xs if math.isfinite(x)]
    ys_all = [y for _, ys in clean.values() for y in ys if math.isfinite(y)]
    if not xs_all or not ys_all:
        raise RecordError("curves_figure needs at least one finite point")
    xs_all += [float(x) for x in x_include]
    ys_all += [float(y) for y in y_include]
    img = _canvas(title, size)
    width, height = size
    # the x axis ends at the data (2,003,200 frames must not stretch it to a 2.5M tick)
    x_hi = max(xs_all)
    x_ticks = _ticks(min(xs_all), x_hi)
    x_ticks = [t for t in x_ticks if t <= x_hi + 1e-9 * abs(x_hi)] or x_ticks
    x_hi = max(x_hi, x_ticks[-1])
    y_ticks = _ticks(min(ys_all), max(ys_all))
    ax = _Axes(img, 100, 80, width - 40, height - 80, (x_ticks[0], x_hi), (y_ticks[0], y_ticks[-1]))
    ax.y_axis(y_ticks, ylabel)
    ax.x_ticks(x_ticks, xlabel)
    entries = []
    for k, (name, (xs, ys)) in enumerate(clean.items()):
        colour = PALETTE[k % len(PALETTE)]
        runs, run = [], []
        for x, y in zip(xs, ys):
            if math.isfinite(x) and math.isfinite(y):
                run.append(ax.px(x, y))
            elif run:
                runs.append(run)
                run = []
        runs.append(run)
        for r in runs:
            if len(r) > 1:
                cv2.polylines(img, [np.array(r, np.int32)], False, colour, 2, cv2.LINE_AA)
            elif r:
                cv2.circle(img, r[0], 3, colour, -1, cv2.LINE_AA)
        entries.append((name, colour, "line"))
    ax.frame()
    # the legend inside the plot's top-left corner, one entry per line
    for k, (name, colour, _) in enumerate(entries):
        y = ax.top + 16 + 20 * k
        cv2.line(img, (ax.left + 10, y), (ax.left + 34, y), colour, 2, cv2.LINE_AA)
        _text(img, name, (ax.left + 42, y), 0.45, valign="middle")
    return _write_png(path, img)


# ------------------------------------------------------------------------------------------------
# The paper's figures from the table's runs

TSNE_SIZE = (1200, 900)  # more room than FIGURE_SIZE: a label per object type


def _run_dir(path, what: str) -> Path:
    path = Path(path)
    if not path.is_dir():
        raise RecordError(f"{path}: no such {what} run directory")
    return path


def read_episodes(eval_dir) -> list[dict]:
    """Every episode of an evaluation run: the JSON lines of eval_dir/episodes/<kitchen>.jsonl."""
    eval_dir = _run_dir(eval_dir, "evaluation")
    files = sorted((eval_dir / "episodes").glob("*.jsonl"))
    if not files:
        raise RecordError(f"{eval_dir} holds no episodes/*.jsonl: not a finished evaluation run")
    episodes = []
    for path in files:
        try:
            lines = path.read_text().splitlines()
        except (OSError, UnicodeDecodeError) as e:
            raise RecordError(f"cannot read {path}: {e}") from e
        for n, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            try:
                episode = json.loads(line)
                if not isinstance(episode, dict):
                    raise ValueError("not a JSON object")
                episodes.append(episode)
            except ValueError as e:
                raise RecordError(f"{path}, line {n}: not an episode ({e})") from e
    return episodes


def unseen_kitchen_stats(episodes: list[dict], where="episodes") -> tuple[float, float] | None:
    """(mean collisions per episode, % of episodes whose last view shows the target) over the
    episodes in unseen kitchens; None where there are none."""
    unseen = [e for e in episodes if e.get("column") == "unseen_kitchens"]
    if not unseen:
        return None
    try:
        collisions = sum(float(e["collisions"]) for e in unseen) / len(unseen)
        shown = 100.0 * sum(bool(e["last_view_shows_target"]) for e in unseen) / len(unseen)
    except (KeyError, TypeError, ValueError) as e:
        raise RecordError(
            f"{where}: an unseen-kitchens episode lacks collisions or last_view_shows_target ({e})"
        ) from e
    return collisions, shown


def _kg_checkpoint(train_dir: Path) -> tuple[dict, Path] | None:
    """The best-validation checkpoint of a training run when its model has an accumulated knowledge
    graph, else None."""
    from .train import TrainError, load_checkpoint  # lazily: recording must not cost a trainer import

    path = train_dir / "best.pt"
    if not path.exists():
        path = train_dir / "last.pt"  # a run stopped before its first validation
    if not path.exists():
        return None
    try:
        ck = load_checkpoint(path)
    except TrainError as e:
        raise RecordError(str(e)) from e
    config = ck["model_config"]
    if config.get("kg", "none") == "none" or config.get("kg_graph") != "accumulated":
        return None
    return ck, path


def gcn_node_features(ck: dict, where="checkpoint") -> tuple[torch.Tensor, torch.Tensor]:
    """The third GCN layer's node features H (125, d) of a KG checkpoint over its accumulated
    co-visibility graph, and that graph's 0/1 adjacency (125, 125)."""
    from . import models  # lazily, as above

    try:
        net = models.make_model(models.ModelConfig(**ck["model_config"]))
        net.load_state_dict(ck["model"])
        covis = models.CoVisibility()
        covis.load_state_dict(ck["covis"])
    except (RuntimeError, KeyError, TypeError, ValueError) as e:
        raise RecordError(f"{where} does not fit its model ({models.first_line(e)})") from e
    net.eval()
    adjacency = covis.adjacency()
    with torch.no_grad():
        h = net.kg.node_features(models.normalized_adjacency(adjacency))
    return h.float(), adjacency


def figures(rows: list[tuple[str, str | None, str]], out_dir, seed: int = 0, progress=print) -> list[Path]:
    """The paper's figures as PNGs in out_dir from rows (Table I row name, training run dir or None,
    evaluation run dir):
      * collisions_unseen.png  mean collisions per episode in unseen kitchens (bars) and the rate of
                               episodes whose last view shows the target (line), per row that has
                               unseen-kitchen episodes;
      * tsne_gcn.png           a t-SNE (seed) of the third GCN layer's node features of the last row
                               trained with an accumulated knowledge graph, the object types that have
                               a co-visibility edge, each labelled;
      * training_curves.png    validation SR (the training episodes' SR for a run without validation)
                               and training_reward.png mean reward per frame, vs frames, per trained row.
    A figure without data is skipped with a note to `progress`. Returns the paths written."""
    from .kitchens import object_types  # a data file read; nothing heavy

    out_dir = Path(out_dir)
    # read everything first: bad input fails before any figure is (re)written
    unseen, metrics, trained = [], {}, []
    for name, train_dir, eval_dir in rows:
        stats = unseen_kitchen_stats(read_episodes(eval_dir), f"{eval_dir}")
        if stats is not None:
            unseen.append((name, *stats))
        if train_dir:
            train_dir = _run_dir(train_dir, "training")
            metrics[name] = read_metrics(train_dir / "metrics.csv")
            trained.append((name, train_dir))
    written = []

    if unseen:
        written.append(
            bar_line_figure(
                [n for n, _, _ in unseen],
                [c for _, c, _ in unseen],
                [s for _, _, s in unseen],
                out_dir / "collisions_unseen.png",
                "Unseen kitchens: collisions per episode and last view showing the target",
                "collisions per episode",
                "last view shows target (%)",
            )
        )
    else:
        progress("figures: no row has unseen-kitchen episodes; collisions_unseen.png skipped")

    kg = None
    for name, train_dir in reversed(trained):  # the last KG row: +KG+Attention in Table I
        found = _kg_checkpoint(train_dir)
        if found is not None:
            kg = (name, *found)
            break
    if kg is None:
        progress("figures: no row trained a knowledge graph; tsne_gcn.png skipped")
    else:
        name, ck, path = kg
        h, adjacency = gcn_node_features(ck, str(path))
        keep = (adjacency.sum(1) > 0).nonzero().squeeze(1)
        if len(keep) < 3:  # no co-visibility yet: every type
            keep = torch.arange(len(h))
        types = object_types()
        y = tsne(h[keep], seed=seed)
        written.append(
            scatter_figure(
                y,
                [types[i] for i in keep.tolist()],
                out_dir / "tsne_gcn.png",
                f"t-SNE of the third GCN layer's node features: {name}, {len(keep)} object types "
                f"({int(ck['frames']):,} frames)",
                size=TSNE_SIZE,
            )
        )

    # validation SR where the run measured it (the checkpoint selection's number), else training SR
    success, reward, validated = {}, {}, 0
    for name, series in metrics.items():
        xs, ys = series.get("val_sr", ([], []))
        if xs:
            success[name] = (xs, ys)
            validated += 1
        elif series.get("success_rate", ([], []))[0]:
            success[f"{name} (training episodes)"] = series["success_rate"]
        if series.get("mean_reward", ([], []))[0]:
            reward[name] = series["mean_reward"]
    # a run that never succeeded draws its line on the x axis, under the others: the legend says so
    success = {(f"{n} (0 throughout)" if not any(ys) else n): (xs, ys) for n, (xs, ys) in success.items()}
    success_title = "Validation success rate during training" if validated else "Success rate during training"
    for curves, file, title, ylabel, y_include in (
        (success, "training_curves.png", success_title, "success rate (%)", (0,)),
        (reward, "training_reward.png", "Mean reward per frame during training", "mean reward per frame", ()),
    ):
        if curves:
            written.append(
                curves_figure(
                    curves, out_dir / file, title, "frames", ylabel, x_include=(0,), y_include=y_include
                )
            )
        else:
            progress(f"figures: no training run logged {ylabel}; {file} skipped")
    return written


def figures_of_table(
    preset: str = "quick", runs_dir="runs", out_dir="docs/figures", spec_path=None, progress=print
) -> list[Path]:
    """The figures of a Table I preset's runs (run_table: finished runs are only reloaded, missing
    ones are trained and evaluated first), from each row's first seed."""
    from . import table  # lazily: the table stage imports the trainer

    spec = table.load_spec(spec_path) if spec_path else table.load_spec()
    result = table.run_table(spec, preset, runs_dir, progress)
    rows = [(r.row.name, r.train_runs[0] or None, r.eval_runs[0]) for r in result.rows]
    return figures(rows, out_dir, progress=progress)
