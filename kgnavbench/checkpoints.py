"""Stage 36 — checkpoints: every kept snapshot of a table's runs, evaluated, as one CSV and a figure.

A run of the paper presets keeps its weights every 2.5M frames (`keep_every`: RUN/snapshots/
frames-N.pt) and measures its validation SR at each of them (metrics.csv). This stage evaluates every
snapshot on the table's fixed episodes, a few per target (5 by default, about 1,900 episodes per
snapshot of a learned row), and writes one CSV line per snapshot: the row, seed and run, the frames,
the validation SR the trainer measured there, whether best.pt and last.pt are that snapshot, and the
SR, SPL and episodes of each of Table I's cells. Any checkpoint rule, the paper's (highest validation
SR, ties to the later), the one-standard-error reading, the final weights or a fixed frame count, is
then a replay over the CSV (`replay`), with no training and no evaluation.

Table I's rule picks each run's checkpoint by its own validation peak, so two rows' cells can differ by
when those peaks came. `matched` compares the spec's pairs of rows at the same frame counts instead:
at each snapshot both rows' runs kept, other - base per cell, with the interval Table I's comparisons
get (each row's stratified bootstrap over seeds and episodes, differenced), from the snapshots'
evaluations (tables/checkpoints-<preset>-matched.csv).

The snapshots live in the runs folder, not in git (16 per run would pass 600 MB), and that folder can
be lost: evaluate a run's snapshots as soon as it finishes. The CSV (tables/checkpoints-<preset>.csv)
is what is committed; a run's lines replace that run's earlier ones, the others are kept.
"""

from __future__ import annotations

import csv
import io
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from .evaluate import evaluate
from .files import atomic_write, duration_text
from .intervals import difference, standard_error, verdict
from .jobs import eval_config, find_trained, only_rows, preset_rows, row_options, trains
from .metrics import COLUMNS, KINDS
from .plots import FigureError, curves_image, write_png
from .record import RecordError, read_metrics
from .runs import load_checkpoint
from .store import read_record
from .table_spec import CELL_KEYS, METRICS, Row, TableError, TableSpec
from .table_statistics import RowResult, cell_episodes, cell_statistics, paper_difference

EPISODES_PER_TARGET = 5
CELLS = tuple(f"{column}_{kind}" for kind in KINDS for column in COLUMNS)
FIELDS = (
    "row",
    "seed",
    "run",
    "frames",
    "val_sr",
    "val_episodes",
    "best",  # 1 where the run's best.pt is this snapshot (the trainer's rule), else 0
    "last",  # 1 where last.pt is: the final weights
    *(f"{cell}_{m}" for cell in CELLS for m in ("sr", "spl", "episodes")),
)
RULES = ("best", "one-se", "last")  # what `replay` reads: Table I's rule, its other reading, final weights


def evaluating_preset(spec: TableSpec, name: str):
    """The preset `name`, one that evaluates its runs under the protocol's rule: a preset that only
    rescores another's evaluations (`score_rule`) is refused, since these lines would not be scored
    its way."""
    preset = spec.preset(name)
    if preset.score_rule:
        raise TableError(
            f"preset {name!r} scores another preset's evaluations under the {preset.score_rule!r} "
            "rule; read the snapshots under the preset that evaluates them"
        )
    return preset


def snapshot_point(frames: int, keep_every: int) -> int:
    """The multiple of keep_every that a snapshot kept at `frames` stands for: the trainer keeps one at
    the first update past each multiple, so seeds (IL's episodes end where they end) and rows keep it
    at other frames; seeds' and rows' snapshots of one point are compared and drawn as one. Without
    keep_every (0), the frames themselves."""
    return frames // keep_every * keep_every if keep_every > 0 else frames


def run_keep_every(run_dir: Path) -> int:
    """The keep_every a run trained with (its config.json's options; 0: none): a run found for a
    preset may have kept snapshots at another spacing, since keep_every changes no weight."""
    options = read_record(run_dir / "config.json", ("options",), TableError)["options"]
    return int(options.get("keep_every") or 0) if isinstance(options, dict) else 0


def preset_keep_every(spec: TableSpec, preset_name: str) -> dict[str, int]:
    """{row name: the keep_every the preset trains it with} (0: none), for the figure."""
    preset = spec.preset(preset_name)
    return {row.name: int(row_options(preset, row).get("keep_every") or 0) for row in spec.rows}


def snapshot_frames(run_dir: Path) -> list[int]:
    """The frames of the snapshots a run kept, in order."""
    frames = []
    for path in (run_dir / "snapshots").glob("frames-*.pt"):
        number = path.stem.removeprefix("frames-")
        if number.isdigit():
            frames.append(int(number))
    return sorted(frames)


def validation_at(run_dir: Path) -> dict[int, tuple[float, int]]:
    """{frames: (validation SR %, episodes)} from a run's metrics.csv."""
    try:
        series = read_metrics(run_dir / "metrics.csv")
    except RecordError as e:
        raise TableError(str(e)) from e
    frames, srs = series.get("val_sr", ([], []))
    counts = dict(zip(*series.get("val_episodes", ([], []))))
    return {f: (sr, int(counts.get(f, 0))) for f, sr in zip(frames, srs)}


def _checkpoint_frames(path: Path) -> int | None:
    return int(load_checkpoint(path)["frames"]) if path.is_file() else None


@dataclass(frozen=True)
class SnapshotRun:
    """One finished run of a preset's row and seed whose kept snapshots are evaluated: on the table's
    fixed episodes (`episodes` per target), on `device`, kept in runs_dir/eval (they resume, as
    every evaluation does)."""

    spec: TableSpec
    preset_name: str
    row: Row
    seed: int
    run_dir: Path
    runs_dir: Path
    episodes: int = EPISODES_PER_TARGET
    device: str = "cpu"

    def evaluations(self):
        """(frames, evaluation) for each snapshot the run kept, in order of frames, each evaluated or
        read back from runs_dir/eval where it was."""
        preset = self.spec.preset(self.preset_name)
        options = row_options(preset, self.row)
        for frames in snapshot_frames(self.run_dir):
            config = eval_config(
                self.spec,
                preset,
                self.row,
                seed=self.seed,
                options=options,
                run_dir=self.run_dir,
                device=self.device,
                checkpoint=f"frames-{frames}",
                episodes=self.episodes,
            )
            yield frames, evaluate(config, self.runs_dir, progress=lambda _line: None)

    def episodes_by_frames(self) -> dict:
        """{frames: that snapshot's episodes per cell} (the snapshots `evidence` evaluated are read,
        not run again; one not yet evaluated is evaluated)."""
        return {frames: cell_episodes(result.results) for frames, result in self.evaluations()}


def run_lines(snapshot_run: SnapshotRun, progress=print, csv_path: Path | None = None) -> list[dict]:
    """One CSV line per snapshot of one finished run; with `csv_path`, each line is merged into it as
    it comes."""
    row, seed, run_dir = snapshot_run.row, snapshot_run.seed, snapshot_run.run_dir
    validation = validation_at(run_dir)
    best, last = _checkpoint_frames(run_dir / "best.pt"), _checkpoint_frames(run_dir / "last.pt")
    lines = []
    todo = len(snapshot_frames(run_dir))
    progress(
        f"{row.name} seed {seed}: {todo} snapshots of {run_dir.name}, {snapshot_run.episodes} episodes "
        "per target each (those evaluated before are read back)"
    )
    evaluating: list[float] = []  # the seconds of each snapshot evaluated in this process
    start = time.perf_counter()
    for n, (frames, result) in enumerate(snapshot_run.evaluations(), 1):
        took = time.perf_counter() - start
        if result.steps:  # evaluated now, not read back
            evaluating.append(took)
        left = max(todo - n, 0)  # (an unfinished run may keep a snapshot meanwhile)
        eta = ""
        if evaluating and left:
            eta = f", about {duration_text(sum(evaluating) / len(evaluating) * left)} left for this run"
        val_sr, val_episodes = validation.get(frames, (math.nan, 0))
        line = {
            "row": row.name,
            "seed": seed,
            "run": run_dir.name,
            "frames": frames,
            "val_sr": val_sr,
            "val_episodes": val_episodes,
            "best": int(frames == best),
            "last": int(frames == last),
        }
        for (column, kind), m in result.summary.items():
            cell = f"{column}_{kind}"
            line.update({f"{cell}_sr": m.sr, f"{cell}_spl": m.spl, f"{cell}_episodes": m.episodes})
        shown = ", ".join(
            f"{c.replace('_static', '')} {line[f'{c}_sr']:.1f}%"
            for c in CELLS
            if c.endswith("static") and f"{c}_sr" in line
        )
        progress(
            f"{row.name} seed {seed} {frames:,} frames: validation {val_sr:.1f}%, {shown} "
            f"({n}/{max(todo, n)}, {took:.0f} s{eta})"
        )
        lines.append(line)
        if csv_path is not None:
            merge_csv(csv_path, [line])
        start = time.perf_counter()
    return lines


def merge_csv(path: Path, new: list[dict]) -> list[dict]:
    """`new` lines into the CSV at `path`, each replacing the line of its run and frames; read just
    before the write, so that two processes evaluating other runs keep each other's lines."""
    keys = {(line["run"], line["frames"]) for line in new}
    lines = [line for line in read_csv(path) if (line["run"], line["frames"]) not in keys] + new
    write_csv(path, lines)
    return lines


def run_with_snapshots(preset, row, seed, runs_dir, device, progress, unfinished=False) -> Path | None:
    """The finished run of one row and seed in `runs_dir` (`unfinished`: or the one still training),
    if it kept snapshots; else None, with a line that names why."""
    try:
        run_dir = find_trained(
            preset, row, seed, row_options(preset, row), runs_dir, device, lambda _line: None, unfinished
        )
    except TableError as e:
        progress(f"skipped: {e}")
        return None
    if not snapshot_frames(run_dir):
        keep_every = run_keep_every(run_dir)
        why = (
            f"its snapshots/ folder holds none, though it trained with keep_every={keep_every} (deleted, "
            "or a zoo copy, which ships best.pt and last.pt only)"
            if keep_every
            else "it trained without keep_every"
        )
        progress(f"skipped: {run_dir} kept no snapshot: {why}")
        return None
    return run_dir


def evidence(
    spec: TableSpec,
    preset_name: str,
    runs_dir: Path,
    csv_path: Path,
    episodes: int = EPISODES_PER_TARGET,
    rows: tuple[str, ...] = (),
    device: str = "cpu",
    progress=print,
    seeds: tuple[int, ...] = (),
    unfinished: bool = False,
) -> list[dict]:
    """Evaluate the snapshots of every finished run of the preset's learned rows (or of `rows`, and of
    `seeds`) found in `runs_dir`, and merge their lines into `csv_path` snapshot by snapshot. A job with
    no finished run there, or a run that kept no snapshot, is named and skipped. `unfinished`: also
    evaluate the snapshots that runs still training have kept so far, writing no line for them (their
    best.pt and last.pt are not final): once the run finishes, a call without it finds those
    evaluations done and writes the lines."""
    # one thread: a snapshot's batches are a kitchen's ~170 episodes, too small to share, and beside a
    # training two threads spin against it (measured: 27 times slower per kitchen than one thread)
    torch.set_num_threads(1)
    preset = evaluating_preset(spec, preset_name)
    unknown = sorted(set(rows) - {row.name for row in spec.rows})
    if unknown:
        raise TableError(f"no row named {', '.join(map(repr, unknown))} in {spec.path}")
    # a row of the spec that the preset does not train is named; a seed no row of them trains, refused
    most = max(preset.seeds_of(row.name) for row in only_rows(spec, preset, rows))
    if any(not 0 <= seed < most for seed in seeds):
        raise TableError(
            f"preset {preset_name!r} trains seeds 0..{most - 1}"
            + (f" of {', '.join(rows)}" if rows else "")
            + ", not "
            + ", ".join(str(seed) for seed in seeds if not 0 <= seed < most)
        )
    read_csv(csv_path)  # a damaged CSV is refused before anything is evaluated
    for row in preset_rows(spec, preset):
        if (rows and row.name not in rows) or not trains(row):
            continue
        for seed in range(preset.seeds_of(row.name)):
            if seeds and seed not in seeds:
                continue
            run_dir = run_with_snapshots(preset, row, seed, runs_dir, device, progress, unfinished)
            if run_dir is None:
                continue
            finished = (run_dir / "finished.json").exists()
            out = csv_path if finished else None  # an unfinished run's lines wait for its end
            snapshot_run = SnapshotRun(spec, preset_name, row, seed, run_dir, runs_dir, episodes, device)
            run_lines(snapshot_run, progress, out)
    return read_csv(csv_path)


MATCHED_FIELDS = (
    "base",
    "other",
    "frames",
    "base_seeds",
    "other_seeds",
    "cell",
    "metric",
    "paper_difference",  # the paper's other - base in this cell (its Table I: best-validation weights)
    "difference",  # ours at these frames: mean over seeds, other - base, in points
    "low",
    "high",
    "verdict",
)


def matched(
    spec: TableSpec,
    preset_name: str,
    runs_dir: Path,
    episodes: int = EPISODES_PER_TARGET,
    rows: tuple[str, ...] = (),
    device: str = "cpu",
    progress=print,
) -> list[dict]:
    """For each comparison of the spec whose two rows the preset trains (with `rows`: those that
    involve one of them), other - base at every snapshot (`snapshot_point`; frames: the seeds' mean)
    where every finished seed of both rows kept a snapshot, per cell and metric: the mean over seeds
    with its 95% interval and verdict, computed as Table I's comparisons are (each row's stratified
    bootstrap over seeds and episodes, in the row's and cell's own stream, differenced), on the
    snapshot evaluations' episodes (`episodes` per target: wider intervals than the table's 100).
    base_seeds and other_seeds count the seeds used; a seed without a finished run, and a snapshot
    some seed lacks, are named and left out. The intervals are each valid on their own; frames share
    streams, so they are no joint band."""
    torch.set_num_threads(1)  # as `evidence`: a snapshot's batches are too small to share
    preset = evaluating_preset(spec, preset_name)
    trained = {row.name: row for row in preset_rows(spec, preset) if trains(row)}
    # row name -> per finished seed: (its run's keep_every, {frames: cells})
    snapshots: dict[str, list[tuple[int, dict]]] = {}

    def row_snapshots(name: str) -> list[tuple[int, dict]]:
        if name not in snapshots:
            snapshots[name] = []
            row = trained[name]
            for seed in range(preset.seeds_of(name)):
                run_dir = run_with_snapshots(preset, row, seed, runs_dir, device, progress)
                if run_dir is None:
                    continue
                snapshot_run = SnapshotRun(spec, preset_name, row, seed, run_dir, runs_dir, episodes, device)
                got = snapshot_run.episodes_by_frames()
                progress(f"{name} seed {seed}: {len(got)} snapshots ({run_dir.name})")
                snapshots[name].append((run_keep_every(run_dir), got))
        return snapshots[name]

    lines = []
    for comparison in spec.comparisons:
        pair = (comparison.base, comparison.other)
        if not all(name in trained for name in pair) or (rows and not set(rows) & set(pair)):
            continue
        base, other = row_snapshots(comparison.base), row_snapshots(comparison.other)
        label = f"{comparison.other} - {comparison.base}"
        if not base or not other:
            missing = comparison.base if not base else comparison.other
            progress(f"skipped: {label}: {missing} has no finished run with snapshots in {runs_dir}")
            continue
        by_point = [
            {snapshot_point(f, keep): (f, cells) for f, cells in got.items()} for keep, got in base + other
        ]
        common = set.intersection(*map(set, by_point))
        lost = sorted({f for seed in by_point for point, (f, _) in seed.items() if point not in common})
        if lost:
            named = ", ".join(f"{f:,}" for f in lost)
            progress(f"{label}: frames {named} left out (not every seed of both rows kept a snapshot there)")
        for point in sorted(common):
            at = [seed[point] for seed in by_point]
            lines += compared_at(
                trained[comparison.base],
                [cells for _, cells in at[: len(base)]],
                trained[comparison.other],
                [cells for _, cells in at[len(base) :]],
                round(sum(f for f, _ in at) / len(at)),  # the seeds' mean: their frames where all are equal
                spec.protocol.margin,
            )
        progress(f"{label}: {len(common)} matched snapshots ({len(other)} and {len(base)} seeds)")
    return lines


def compared_at(
    base: Row, base_episodes: list[dict], other: Row, other_episodes: list[dict], frames: int, margin: float
):
    """other - base at one frame count, per cell and metric, from each row's episodes per seed ("column/
    kind" -> EpisodeValues, as `cell_episodes` gives): the lines of `matched`, computed as Table I's
    comparisons are (`table_statistics`: each row's own bootstrap stream, differenced), the verdicts at
    the spec's `margin`."""
    stats = {
        name: {cell: cell_statistics(RowResult(row, per_seed, [], [], 0.0), cell) for cell in CELL_KEYS}
        for name, row, per_seed in (("base", base, base_episodes), ("other", other, other_episodes))
    }
    lines = []
    for cell in CELL_KEYS:
        for metric in METRICS:
            b, o = stats["base"][cell][metric], stats["other"][cell][metric]
            if b.bootstrap is None or o.bootstrap is None:
                continue  # a cell without episodes for one of the rows, as Table I leaves it
            ours = difference(b.bootstrap, o.bootstrap)
            paper = paper_difference(base, other, cell, metric)
            lines.append(
                {
                    "base": base.name,
                    "other": other.name,
                    "frames": frames,
                    "base_seeds": len(base_episodes),
                    "other_seeds": len(other_episodes),
                    "cell": cell,
                    "metric": metric,
                    "paper_difference": math.nan if paper is None else paper,
                    "difference": ours.estimate,
                    "low": ours.low,
                    "high": ours.high,
                    "verdict": verdict(paper, ours.low, ours.high, margin),
                }
            )
    return lines


def merge_matched_csv(path: Path, new: list[dict]) -> list[dict]:
    """`new` lines into the matched CSV at `path`: each comparison in `new` replaces that comparison's
    lines, the others' are kept (a call for some rows loses no other pair's evidence)."""
    pairs = {(line["base"], line["other"]) for line in new}
    kept = []
    if Path(path).exists():
        try:
            with Path(path).open(newline="") as f:
                reader = csv.DictReader(f)
                if tuple(reader.fieldnames or ()) != MATCHED_FIELDS:
                    raise TableError(f"{path} is not a matched checkpoints CSV (its columns differ)")
                kept = [line for line in reader if (line["base"], line["other"]) not in pairs]
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise TableError(f"cannot read {path}: {e}") from e
    lines = kept + [{key: _cell(line[key]) for key in MATCHED_FIELDS} for line in new]
    out = io.StringIO()
    writer = csv.DictWriter(out, MATCHED_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(lines)
    atomic_write(Path(path), out.getvalue())
    return lines


def _cell(value) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else f"{value:.4f}"
    return str(value)


def write_csv(path: Path, lines: list[dict]) -> None:
    """The CSV in the spec's row order is not known here: lines sorted by row name, seed and frames."""
    out = io.StringIO()
    writer = csv.DictWriter(out, FIELDS, lineterminator="\n")
    writer.writeheader()
    for line in sorted(lines, key=lambda x: (str(x["row"]), int(x["seed"]), int(x["frames"]))):
        writer.writerow({key: _cell(line.get(key, "")) for key in FIELDS})
    atomic_write(Path(path), out.getvalue())


def read_csv(path: Path) -> list[dict]:
    """The lines of a checkpoints CSV (none if it does not exist), numbers as numbers; a file that is
    not one is a TableError naming it and the line."""
    path = Path(path)
    if not path.exists():
        return []
    try:
        reader = csv.DictReader(io.StringIO(path.read_text()))
        rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise TableError(f"cannot read {path}: {e}") from e
    missing = [f for f in ("row", "seed", "run", "frames", "val_sr") if f not in (reader.fieldnames or [])]
    if missing:
        raise TableError(f"{path} is not a checkpoints CSV: no {', '.join(missing)} column")
    lines = []
    for n, raw in enumerate(rows, start=2):
        try:
            line: dict = {"row": raw["row"], "run": raw["run"], "seed": int(raw["seed"])}
            for key in FIELDS[3:]:
                text = (raw.get(key) or "").strip()
                if key in ("frames", "val_episodes", "best", "last") or key.endswith("_episodes"):
                    line[key] = int(text) if text else 0
                else:
                    line[key] = float(text) if text else math.nan
        except (TypeError, ValueError) as e:
            raise TableError(f"{path}, line {n}: not a number ({e})") from e
        lines.append(line)
    return lines


def replay(lines: list[dict], rule: str) -> dict[str, dict]:
    """{run: the line of the snapshot `rule` selects}: "best", the highest validation SR, ties to the
    later (Table I's rule, what the trainer kept as best.pt); "one-se", the latest snapshot whose
    validation SR is within one standard error of the best so far; "last", the final weights."""
    if rule not in RULES:
        raise TableError(f"unknown checkpoint rule {rule!r}; choose one of {', '.join(RULES)}")
    chosen: dict[str, dict] = {}
    by_run: dict[str, list[dict]] = {}
    for line in lines:
        by_run.setdefault(line["run"], []).append(line)
    for run, run_lines_ in by_run.items():
        ordered = sorted(run_lines_, key=lambda x: x["frames"])
        if rule == "last":
            chosen[run] = ordered[-1]
            continue
        best_sr, pick = -math.inf, None
        for line in ordered:
            sr = line["val_sr"]
            if math.isnan(sr):
                continue
            best_sr = max(best_sr, sr)
            if rule == "best" and sr >= best_sr:
                pick = line
            if rule == "one-se" and sr >= best_sr - standard_error(best_sr, max(line["val_episodes"], 1)):
                pick = line
        if pick is not None:
            chosen[run] = pick
    return chosen


FIGURE_SERIES = (  # (CSV cell, legend): the static targets' columns, as Table I's first three
    ("val_sr", "validation (unseen kitchens)"),
    ("seen_seen_static_sr", "seen kitchens, seen targets"),
    ("seen_unseen_static_sr", "seen kitchens, unseen targets"),
    ("unseen_kitchens_static_sr", "unseen kitchens"),
)
# FF A3C has heads for its training kitchens only, so it validates on their seen targets (train.py)
FF_VALIDATION_LEGEND = "validation (its training kitchens, seen targets)"
PANEL_SIZE = (760, 420)
PANELS_PER_LINE = 3


def row_curves(lines: list[dict], keep_every: int = 0) -> dict[str, tuple[list[float], list[float]]]:
    """One row's curves for the figure: per FIGURE_SERIES legend, (frames in millions, SR %), the mean
    over the seeds' snapshots at each point (`snapshot_point`; x: their mean frames)."""
    points: dict[int, list[dict]] = {}  # snapshot point -> the seeds' snapshots there
    for x in lines:
        points.setdefault(snapshot_point(x["frames"], keep_every), []).append(x)
    at = [points[k] for k in sorted(points)]
    xs = [sum(x["frames"] for x in group) / len(group) / 1e6 for group in at]
    series = {}
    for key, legend in FIGURE_SERIES:
        ys = []
        for group in at:
            values = [x[key] for x in group if not math.isnan(x.get(key, math.nan))]
            ys.append(sum(values) / len(values) if values else math.nan)
        if any(math.isfinite(y) for y in ys):
            series[legend] = (xs, ys)
    return series


def panel_series(lines: list[dict], keep_every: int = 0) -> dict[str, tuple[list[float], list[float]]]:
    """`row_curves`, with FF A3C's validation named for where it is measured."""
    series = row_curves(lines, keep_every)
    if lines and all(x["run"].startswith("ff_a3c-") for x in lines):
        series = {FF_VALIDATION_LEGEND if k == FIGURE_SERIES[0][1] else k: v for k, v in series.items()}
    return series


def figure(
    lines: list[dict],
    path: Path,
    row_order: list[str] | None = None,
    keep_every: dict[str, int] | None = None,
) -> Path:
    """Validation SR against each test column's SR over frames, one panel per row (the mean over the
    row's seeds at each snapshot, `keep_every` the row's spacing, `preset_keep_every`; the seeds'
    count in the panel's title)."""
    names = [r for r in (row_order or []) if any(x["row"] == r for x in lines)]
    names += sorted({x["row"] for x in lines} - set(names))
    if not names:
        raise FigureError("no checkpoint lines to draw")
    panels = []
    for name in names:
        mine = [x for x in lines if x["row"] == name]
        series = panel_series(mine, (keep_every or {}).get(name, 0))
        seeds = len({x["seed"] for x in mine})
        title = f"{name} ({seeds} seed{'s' if seeds != 1 else ''})"
        panels.append(curves_image(series, title, "frames (M)", "SR (%)", PANEL_SIZE, (0,), (0, 100)))
    blank = np.full_like(panels[0], 255)
    while len(panels) % PANELS_PER_LINE and len(panels) > PANELS_PER_LINE:
        panels.append(blank)
    grid = [cv2.hconcat(panels[i : i + PANELS_PER_LINE]) for i in range(0, len(panels), PANELS_PER_LINE)]
    return write_png(path, cv2.vconcat(grid) if len(grid) > 1 else grid[0])


MATCHED_PANELS = (  # (cell, panel title): the static targets' columns, SR
    ("seen_seen/static", "seen kitchens, seen targets"),
    ("seen_unseen/static", "seen kitchens, unseen targets"),
    ("unseen_kitchens/static", "unseen kitchens"),
)


def matched_figure(lines: list[dict], path: Path) -> Path:
    """Each comparison's other - base SR over frames with its 95% interval, one line of panels per
    comparison (the static targets' three columns)."""
    comparisons = list(dict.fromkeys((x["other"], x["base"]) for x in lines))
    if not comparisons:
        raise FigureError("no matched comparison to draw")
    grid = []
    for other, base in comparisons:
        panels = []
        for cell, title in MATCHED_PANELS:
            mine = sorted(
                (
                    x
                    for x in lines
                    if (x["other"], x["base"], x["cell"], x["metric"]) == (other, base, cell, "SR")
                ),
                key=lambda x: x["frames"],
            )
            xs = [x["frames"] / 1e6 for x in mine]
            series = {
                f"{other} - {base}": (xs, [x["difference"] for x in mine]),
                "95% interval, low": (xs, [x["low"] for x in mine]),
                "95% interval, high": (xs, [x["high"] for x in mine]),
                "no difference": (xs, [0.0] * len(xs)),
            }
            if not xs:
                panels.append(np.full((PANEL_SIZE[1], PANEL_SIZE[0], 3), 255, np.uint8))
                continue
            panels.append(
                curves_image(series, title, "frames (M)", "SR difference (points)", PANEL_SIZE, (0,), (0,))
            )
        grid.append(cv2.hconcat(panels))
    return write_png(path, cv2.vconcat(grid) if len(grid) > 1 else grid[0])
