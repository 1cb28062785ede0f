"""Stage 18 — table: the paper's Table I from a table spec (`tables/table1.toml`).

The spec (kgnavbench/table_spec.py) names the protocol, the presets, the rows and the comparisons
the paper draws between rows. `run_table` goes row by row and seed by seed: train unless a finished
run with the same config exists (an unfinished one resumes), take the checkpoint with the best
validation SR, evaluate it on the fixed episodes (per-episode JSON lines in the eval run), then write
the table as markdown, CSV and LaTeX. Everything it runs is a resumable run directory, so a killed
`make table` continues where it stopped.

Table I has five cells per row, each SPL and SR in percent (`CELLS`): static targets in seen kitchens
with seen targets, seen kitchens with unseen targets and unseen kitchens; actionable targets in seen
kitchens with seen targets and unseen kitchens (no actionable target of a training kitchen is unseen).
A cell is the mean over seeds of each seed's episode mean, with a 95% stratified bootstrap interval
over seeds and episodes (`intervals`), the paper's number beside it; "–" where there are no episodes or
the paper has none (FF A3C in unseen kitchens). Under the table, each comparison of the spec gets, per
cell and metric, the paper's difference, ours with its interval, and a verdict (holds, reversed, cannot
tell; higher or lower where the paper has no side).
"""

from __future__ import annotations

import concurrent.futures
import csv
import functools
import io
import json
import multiprocessing
import os
import re
import shutil
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from shlex import quote
from typing import NamedTuple

import torch

from . import claims
from .device import DeviceError, name_of, resolve
from .evaluate import (
    COLUMN_TITLES,
    EpisodeResult,
    EvalConfig,
    EvalRun,
    evaluate,
    git_revision,
    spl_term,
)
from .files import atomic_write, checksum_matches, end_with_parent, first_line, one_line
from .intervals import (
    REPLICATES,
    VERDICTS,
    Bootstrap,
    Interval,
    difference,
    joint_stratified_bootstrap,
    verdict,
)
from .kitchens import KITCHEN_NAMES
from .plugins import PluginError, load_plugin
from .runs import (
    POLICY_KEYS,
    TrainError,
    checkpoint_differences,
    load_checkpoint,
    run_directory,
    run_record,
    save_checkpoint,
    train_method,
    training_kitchens,
)
from .table_spec import (
    CELL_KEYS,
    CELL_TITLES,
    CELLS,
    METRICS,
    PERCENT,
    SPEC_FILE,
    Comparison,
    Preset,
    Row,
    TableError,
    TableSpec,
)
from .tasks import load_task_file

# ------------------------------------------------------------------------------------------------
# Running the rows


class EpisodeValue(NamedTuple):
    """One episode as a cell's statistics need it: its stratum (kitchen/target: the bootstrap resamples
    episodes within targets) and its success and SPL term, both in percent (0 or 100; 100 * S * L /
    max(P, L))."""

    stratum: str
    success: float
    spl: float

    def value(self, metric: str) -> float:
        """The episode's value for one of METRICS."""
        return {"SPL": self.spl, "SR": self.success}[metric]


def cell_episodes(results: list[EpisodeResult]) -> dict[str, list[EpisodeValue]]:
    """One evaluation's episodes per Table I cell ("column/kind" -> values; a cell without episodes
    has an empty list). Episodes of no cell (validation kitchens) are left out."""
    cells: dict[str, list[EpisodeValue]] = {key: [] for key in CELL_KEYS}
    for r in results:
        key = f"{r.column}/{r.kind}"
        if key in cells:
            cells[key].append(
                EpisodeValue(f"{r.kitchen}/{r.target}", PERCENT * r.success, PERCENT * spl_term(r))
            )
    return cells


@dataclass
class RowResult:
    row: Row
    episodes: list[dict[str, list[EpisodeValue]]]  # per seed: "column/kind" -> its episodes
    train_runs: list[str]
    eval_runs: list[str]
    seconds: float


@dataclass
class TableResult:
    spec: TableSpec
    preset: Preset
    rows: list[RowResult]
    seconds: float
    git_revision: str
    # rows of the preset that this table leaves out (`--row`): a partial table
    left_out: tuple[str, ...] = ()
    _statistics: TableStatistics | None = field(default=None, init=False, repr=False, compare=False)

    def statistics(self) -> TableStatistics:
        """The cells' intervals and the comparisons' verdicts, computed once (the writers share them)."""
        if self._statistics is None:
            self._statistics = table_statistics(self)
        return self._statistics


def eval_kitchens(preset: Preset, row: Row) -> tuple[str, ...]:
    """The preset's evaluation kitchens (all of Table I's by default), without unseen kitchens for a
    method that has no row there."""
    splits = load_task_file()["splits"]
    kitchens = preset.eval_kitchens or tuple(
        sorted(splits["train"] + splits["test"], key=KITCHEN_NAMES.index)
    )
    if not row.unseen_kitchens:
        kitchens = tuple(k for k in kitchens if k in splits["train"])
    return kitchens


@dataclass(frozen=True)
class Sources:
    """Where a job's trained run comes from and what the job does with it: by default it trains (or
    finds, or resumes) the run in the runs folder and evaluates it. `trained`: take the finished run
    from that folder instead (a zoo of shipped runs, or another runs folder) and never train.
    `train_only`: train, and leave evaluating and assembling to a later `table`."""

    trained: Path | None = None
    train_only: bool = False


# what a run's config.json must share with a row's job to be that job's run in a `trained` folder; the
# code's hashes are left out: a shipped run stays usable after later changes to the training code
TRAINED_RUN_KEYS = ("method", "options", "frames", "seed", "kitchens", "world_size", "device")
# options a plugin gained after runs were shipped, with the value that reproduces how those runs
# trained: a shipped run's config without the option is read as having that value
ADDED_OPTIONS = {
    "kg_edges": "binary",
    "kg_readout": "pooled",
    "attention_context": True,
    "attention_heads": 1,
    "gcn_norm": "none",
    "attention_over": "union",
    "attention_bound": 0.0,
}
# options that change no weight of a run (how often it keeps snapshots): not compared
UNWEIGHTED_OPTIONS = ("keep_every",)


def trained_run(folder: Path, record: dict, row_name: str, progress=print) -> Path:
    """The finished run in `folder` (its run folders, or those of its train/) whose config matches
    `record` (`run_record`) on TRAINED_RUN_KEYS. Trained by other code than this checkout's, it is
    used with a line that says from which revision."""
    want = {key: record[key] for key in TRAINED_RUN_KEYS}
    nearest: tuple[int, str] | None = None  # (keys that differ, which) of the closest run, for the error
    candidates = sorted(
        path
        for path in {*folder.glob("*/config.json"), *folder.glob("train/*/config.json")}
        if not path.parent.name.startswith(".")  # a staging folder `ship_run` left, never a run
    )
    for config_path in candidates:
        try:
            config = json.loads(config_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            continue  # not a run's config: nothing to match
        if not isinstance(config, dict) or config.get("method") != record["method"]:
            continue
        differ = [key for key in TRAINED_RUN_KEYS if config.get(key) != want[key]]
        if isinstance(config.get("options"), dict) and "options" in differ:
            options = {
                **{k: v for k, v in ADDED_OPTIONS.items() if k in want["options"]},
                **config["options"],
            }
            differ.remove("options")
            differ += [
                f"options.{k}"
                for k in sorted({*options, *want["options"]} - set(UNWEIGHTED_OPTIONS))
                if options.get(k) != want["options"].get(k)
            ]
        if differ:
            if nearest is None or len(differ) < nearest[0]:
                nearest = (len(differ), f"{config_path.parent} differs in {', '.join(differ[:6])}")
            continue
        run_dir = config_path.parent
        if not (run_dir / "finished.json").exists():
            raise TableError(f"row {row_name!r} (seed {record['seed']}): {run_dir} is not finished")
        if config.get("training_code_sha256") != record["training_code_sha256"]:
            revision = one_line(str(config.get("git_revision", "?")))[:12]
            progress(
                f"{run_dir}: trained by the code of revision {revision}, not this checkout's training "
                "code; used as shipped"
            )
        return run_dir
    hint = f"; the closest, {nearest[1]}" if nearest else ""
    raise TableError(
        f"row {row_name!r} (seed {record['seed']}): no finished {record['method']} run in {folder} "
        f"trained as the preset says{hint}"
    )


# a training run's folder: METHOD-HASH as `runs.run_directory` names it (printable ASCII only)
RUN_FOLDER = re.compile(r"[A-Za-z0-9_+][A-Za-z0-9_.+-]*-[0-9a-f]{10}")
# finished.json last: a staging folder left by a killed ship is never a finished run
SHIPPED_FILES = ("config.json", "metrics.csv", "finished.json")


@dataclass(frozen=True)
class Shipped:
    """A run shipped into a zoo: its folder and what zoo/README.md lists of it."""

    folder: Path
    method: str
    seed: int
    frames: int  # trained
    best_frames: int  # best.pt's


def _json_record(path: Path, keys: tuple[str, ...]) -> dict:
    """A run's JSON file as an object holding `keys`, or a TableError naming the file."""
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise TableError(f"{path.parent} has no {path.name}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise TableError(f"{path} is unreadable ({type(e).__name__}: {one_line(str(e))})") from e
    missing = [key for key in keys if not isinstance(record, dict) or key not in record]
    if missing:
        raise TableError(f"{path} is not a run's {path.name}: no {', '.join(missing)}")
    return record


def _shipped_checkpoint(path: Path) -> dict:
    """The weights-only copy of a run's checkpoint (POLICY_KEYS), or a TableError naming the file."""
    if path.is_file() and checksum_matches(path, path.read_bytes()) is None:
        raise TableError(f"checkpoint {path} has no checksum ({path.name}.sha256); not shipped")
    try:
        ck = load_checkpoint(path)
    except TrainError as e:
        raise TableError(f"{first_line(e).split('; delete')[0]}; not shipped") from e
    missing = [key for key in POLICY_KEYS if key not in ck]
    if missing:
        raise TableError(f"checkpoint {path} has no {', '.join(missing)}; not shipped")
    return {key: ck[key] for key in POLICY_KEYS}


def ship_run(run_dir: Path, zoo: Path, checkpoints: tuple[str, ...] = ("best",)) -> Shipped:
    """Copy a finished training run into `zoo` (one folder, named as the run) as `--trained` and
    `eval --run` read it: config.json, metrics.csv, finished.json and each checkpoint (best.pt, Table
    I's; last.pt with "last") weights-only, as trained (fp32), with its sha256. A checkpoint without its
    checksum, or one that does not match it, is refused, as is a run whose JSON files do not read; the
    folder appears whole or not at all (it is staged in a hidden folder beside it, which `trained_run`
    skips), and an existing one is never replaced."""
    run_dir, zoo = Path(run_dir), Path(zoo)
    if not RUN_FOLDER.fullmatch(run_dir.name):
        raise TableError(
            f"{ascii(run_dir.name)} is not a run folder's name (METHOD-HASH: letters, digits and _.+-, "
            "not first a dot, then a dash and 10 hexadecimal digits); not shipped"
        )
    for name in (*SHIPPED_FILES, *(f"{c}.pt" for c in checkpoints), *(f"{c}.pt.sha256" for c in checkpoints)):
        if (run_dir / name).is_symlink():  # a link could bring any file of the machine into the zoo
            raise TableError(f"{run_dir / name} is a symbolic link; a run's files are shipped as files only")
    if not (run_dir / "config.json").is_file():
        raise TableError(f"{run_dir} is not a training run (no config.json)")
    if not (run_dir / "finished.json").is_file():
        raise TableError(f"{run_dir} is not finished (no finished.json); ship a run once it has finished")
    config = _json_record(run_dir / "config.json", ("method", "seed"))
    finished = _json_record(run_dir / "finished.json", ("frames",))
    if config["method"] != run_dir.name.rsplit("-", 1)[0]:
        raise TableError(
            f"{run_dir}/config.json names the method {ascii(config['method'])}, not the folder's "
            f"{run_dir.name.rsplit('-', 1)[0]!r}; not shipped"
        )
    frames = finished["frames"]
    if not isinstance(frames, int) or isinstance(frames, bool) or frames < 0:
        raise TableError(
            f"{run_dir}/finished.json's frames {ascii(frames)} is not a whole number; not shipped"
        )
    if not (run_dir / "metrics.csv").is_file():
        raise TableError(f"{run_dir} has no metrics.csv")
    weights = {name: _shipped_checkpoint(run_dir / f"{name}.pt") for name in checkpoints}
    for name, state in weights.items():  # a checkpoint is what its config.json says it is
        differ = checkpoint_differences(state, config)
        if differ:
            raise TableError(
                f"{run_dir / name}.pt is not the run its config.json describes: it differs in "
                f"{'; '.join(differ[:4])}"
            )
    out = zoo / run_dir.name
    if out.exists():
        raise TableError(f"{out} exists; a shipped run is never replaced (delete it first to ship again)")
    zoo.mkdir(parents=True, exist_ok=True)
    for stale in zoo.glob(f".{run_dir.name}-*.tmp"):  # left by a killed ship of this run: never a run
        shutil.rmtree(stale, ignore_errors=True)
    staging = Path(tempfile.mkdtemp(dir=zoo, prefix=f".{run_dir.name}-", suffix=".tmp"))
    try:
        os.chmod(staging, 0o755)  # mkdtemp's folder is private; a zoo folder is read by everyone
        for name, state in weights.items():
            save_checkpoint(staging / f"{name}.pt", state)
        for name in SHIPPED_FILES:
            shutil.copyfile(run_dir / name, staging / name)
        os.rename(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    best = weights["best"]["frames"] if "best" in weights else None
    return Shipped(out, str(config["method"]), config["seed"], finished["frames"], best)


def find_trained(
    preset: Preset, row: Row, seed: int, options: dict, folder: Path, device: str, progress=print
) -> Path:
    """The finished run in `folder` (a zoo, or a runs folder) that trained this row's job as the
    preset says (`trained_run`), whatever code revision trained it."""
    plugin = load_plugin(row.method)
    try:
        on = name_of(resolve(device))
    except DeviceError as e:
        raise TableError(str(e)) from e
    record = run_record(
        plugin, plugin.config(options), preset.frames, seed, training_kitchens(preset.train_kitchens), on
    )
    return trained_run(folder, record, row.name, progress)


def eval_config(
    spec: TableSpec,
    preset: Preset,
    row: Row,
    seed: int,
    options: dict,
    run_dir: Path | None,
    device: str = "cpu",
    checkpoint: str | None = None,
    episodes: int | None = None,
) -> EvalConfig:
    """The evaluation of one row's job: the protocol's rules, the preset's kitchens and episodes, and
    the preset's checkpoint rule unless `checkpoint` names another (a snapshot, frames-N)."""
    if checkpoint is None:
        checkpoint = "last" if checkpoint_rule(spec, preset) == "last" else "best"
    return EvalConfig(
        method=row.method,
        options=tuple(sorted(options.items())),
        success_rule=spec.protocol.success_rule,
        stop_ends=spec.protocol.stop_ends,
        split="table",
        kitchens=eval_kitchens(preset, row),
        episodes_per_target=preset.episodes if episodes is None else episodes,
        seed=seed,
        run=str(run_dir) if run_dir else "",
        checkpoint=checkpoint,
        device=device,
        unseen_target_kitchens=preset.unseen_target_kitchens,
    )


def row_options(preset: Preset, row: Row) -> dict:
    """A row's options: a learned row's are the preset's with the row's over them."""
    return {**preset.options, **row.options} if _trains(row) else dict(row.options)


def run_row(
    spec: TableSpec,
    preset: Preset,
    row: Row,
    seed: int,
    runs_dir: Path,
    progress,
    device: str = "cpu",
    sources: Sources = Sources(),
) -> tuple:
    """Train (or find, or resume) one row's run for one seed on `device`, then evaluate its best
    checkpoint (the eval run is None under `sources.train_only`)."""
    options = row_options(preset, row)
    run_dir = None
    if _trains(row):
        if sources.trained is not None:
            run_dir = find_trained(preset, row, seed, options, sources.trained, device, progress)
        else:
            run_dir = train_method(
                row.method,
                options,
                preset.frames,
                seed,
                preset.train_kitchens,
                runs_dir,
                progress=progress,
                device=device,
            )
    if sources.train_only:
        return run_dir, None
    config = eval_config(spec, preset, row, seed, options, run_dir, device)
    if not config.kitchens:  # every evaluation kitchen is an unseen one, where this row has no cells: "–"
        return run_dir, EvalRun(config, Path(runs_dir) / "eval")  # (no kitchens would mean all of them)
    return run_dir, evaluate(config, runs_dir, progress=progress)


def _trains(row: Row) -> bool:
    try:
        return callable(getattr(load_plugin(row.method).module, "train", None))
    except PluginError as e:
        raise TableError(f"row {row.name!r}: {e}") from e


def time_left(done: list[tuple[bool, float]], todo: list[bool]) -> float | None:
    """Seconds left: per kind of row (trained or not), the mean time of the rows of that kind done so
    far times the rows of that kind to come; None while a kind to come has none done (a random walk's
    seconds say nothing about a training run's minutes)."""
    left = 0.0
    for kind in (True, False):
        coming = sum(1 for k in todo if k == kind)
        times = [t for k, t in done if k == kind]
        if coming and not times:
            return None
        left += coming * (sum(times) / len(times) if times else 0.0)
    return left


class JobOutcome(NamedTuple):
    """What the table keeps of one job."""

    cells: dict[str, list[EpisodeValue]]  # "column/kind" -> its episodes
    train_run: str  # "" for a method that does not train
    eval_run: str
    seconds: float
    reused: bool  # found done on disk: its seconds say nothing about a job of its kind


def _job(
    spec: TableSpec,
    preset: Preset,
    row: Row,
    seed: int,
    runs_dir: Path,
    progress,
    threads: int,
    device: str = "cpu",
    sources: Sources = Sources(),
) -> JobOutcome:
    """One row and seed, trained (or found) and evaluated: what the table keeps of it. Runs in the
    table's process or in a worker process (with `threads` torch threads: 1 where jobs run side by
    side, so that they do not wait on each other's cores)."""
    if threads:
        torch.set_num_threads(threads)
    started = time.time()
    t0 = time.perf_counter()
    try:
        run_dir, run = run_row(spec, preset, row, seed, runs_dir, progress, device, sources)
    except PluginError as e:
        raise TableError(f"row {row.name!r}: {e}") from e
    # a row found done on disk took seconds, not what a row of its kind takes: no ETA sample (a
    # shipped run's job is its evaluation)
    if run_dir is not None and sources.trained is None:
        reused = (run_dir / "finished.json").stat().st_mtime < started
    elif run is not None:
        reused = len(run.resumed) == len(run.config.kitchen_list())
    else:
        reused = True
    return JobOutcome(
        cell_episodes(run.results) if run is not None else {},
        str(run_dir) if run_dir else "",
        str(run.directory) if run is not None else "",
        time.perf_counter() - t0,
        reused,
    )


def checkpoint_rule(spec: TableSpec, preset: Preset) -> str:
    """The checkpoint rule a preset's evaluations follow: its own, else the protocol's."""
    return preset.checkpoint or spec.protocol.checkpoint


def preset_rows(spec: TableSpec, preset: Preset) -> list[Row]:
    return [row for row in spec.rows if not preset.rows or row.name in preset.rows]


def table_jobs(spec: TableSpec, preset: Preset) -> list[tuple[Row, int]]:
    """The preset's jobs, (row, seed) each, in the table's order: job N (from 1) is the N-th."""
    return [(row, seed) for row in preset_rows(spec, preset) for seed in range(preset.seeds)]


def only_rows(spec: TableSpec, preset: Preset, names: tuple[str, ...]) -> list[Row]:
    """The preset's rows named in `names` (all of them for none), in the spec's order; a TableError
    names a row the preset does not have."""
    rows = preset_rows(spec, preset)
    unknown = [name for name in names if name not in {row.name for row in rows}]
    if unknown:
        raise TableError(
            f"preset {preset.name!r} has no row {', '.join(map(repr, unknown))}; its rows: "
            + "; ".join(row.name for row in rows)
        )
    return [row for row in rows if not names or row.name in names]


def job_claim(
    runs_dir: Path | str, preset: Preset, n: int, row: Row, seed: int, sources: Sources = Sources()
) -> Path:
    """Where job n's claim lives: named by the preset, the job's number, its row and its seed (and
    "train" for training only: a job trained is not a job evaluated)."""
    kind = "train-" if sources.train_only else ""
    return (
        Path(runs_dir)
        / "claims"
        / f"table-{kind}{preset.name}-{n + 1:03d}-{zlib.crc32(row.name.encode()):08x}-s{seed}.claim"
    )


def job_commands(spec: TableSpec, preset_name: str, runs_dir: Path | str) -> list[str]:
    """One shell command per job (for a Slurm array, `xargs -P`, ssh loops): each trains and evaluates
    its row and seed into the shared runs folder; `kgnavbench table` after them only assembles."""
    preset = spec.preset(preset_name)
    jobs = table_jobs(spec, preset)
    spec_option = (
        "" if Path(spec.path).resolve() == SPEC_FILE.resolve() else f" --spec {quote(str(spec.path))}"
    )
    base = f"kgnavbench table --preset {quote(preset.name)}{spec_option} --runs {quote(str(runs_dir))}"
    # every argument quoted for the shell; the row's name only in a comment, on one line
    return [
        f"{base} --job {n + 1}  # {one_line(row.name)} (seed {seed})" for n, (row, seed) in enumerate(jobs)
    ]


def run_job(
    spec: TableSpec,
    preset_name: str,
    number: int,
    runs_dir: Path | str = "runs",
    progress=print,
    device: str = "cpu",
    sources: Sources = Sources(),
) -> None:
    """Job `number` (from 1, as `job_commands` prints it): train (or find, or resume) and evaluate."""
    preset = spec.preset(preset_name)
    jobs = table_jobs(spec, preset)
    if not 1 <= number <= len(jobs):
        raise TableError(f"preset {preset.name!r} has jobs 1..{len(jobs)}, not {number}")
    row, seed = jobs[number - 1]
    progress(f"== [{number}/{len(jobs)}] {row.name} (seed {seed})")
    if sources.trained is None and _trains(row):  # a run trained by other code is not this one
        announce_training(preset, [(row, seed)], Path(runs_dir), device, progress)
    _job(spec, preset, row, seed, Path(runs_dir), progress, preset.threads, device, sources)


def run_worker(
    spec: TableSpec,
    preset_name: str,
    runs_dir: Path | str = "runs",
    progress=print,
    device: str = "cpu",
    sources: Sources = Sources(),
) -> list[int]:
    """Take the next unclaimed job of the preset, run it, mark it done, until none is left; returns
    the numbers (from 1) of the jobs this worker ran. Several workers, on this machine or on others
    that share `runs_dir`, split the jobs between them (`claims`: a job is claimed by one worker; a
    dead worker's claim on this host is taken over)."""
    preset = spec.preset(preset_name)
    jobs = table_jobs(spec, preset)
    ran = []
    for n, (row, seed) in enumerate(jobs):
        # training only: a job of a row that does not train is nobody's, and its claim is not taken
        if sources.train_only and not _trains(row):
            continue
        path = job_claim(runs_dir, preset, n, row, seed, sources)
        if not claims.claim(path):
            continue
        try:
            progress(f"== [{n + 1}/{len(jobs)}] {row.name} (seed {seed}): claimed by pid {os.getpid()}")
            _job(spec, preset, row, seed, Path(runs_dir), progress, preset.threads, device, sources)
        except BaseException:
            claims.release(path)
            raise
        claims.done(path)
        ran.append(n + 1)
    progress(f"== no job of preset {preset.name!r} left to claim; this worker ran {len(ran)}")
    return ran


# frames per second of one core, the paper preset's learned rows measured on the 2-core development
# machine (40M frames in 66-87 core-minutes, docs/speed.md): only to say beforehand what training costs
FRAMES_PER_CORE_SECOND = 8_000


def announce_training(preset: Preset, jobs: list, runs_dir: Path, device: str, progress) -> None:
    """Before anything trains, one line: how many of the jobs' runs are not finished in `runs_dir`
    (they will train, or resume) and about how many core-hours that is, so that hours of work never
    start without a word."""
    try:
        on = name_of(resolve(device))
    except DeviceError as e:
        raise TableError(str(e)) from e
    to_train = 0
    for row, seed in jobs:
        try:
            plugin = load_plugin(row.method)
            options = {**preset.options, **row.options}
            config = plugin.config(options)
            record = run_record(
                plugin, config, preset.frames, seed, training_kitchens(preset.train_kitchens), on
            )
        except (PluginError, TrainError, ValueError):
            continue  # the job itself names what is wrong, with its row
        to_train += not (run_directory(runs_dir, record) / "finished.json").exists()
    if to_train:
        hours = to_train * preset.frames / FRAMES_PER_CORE_SECOND / 3600
        progress(
            f"== training {to_train} of the preset's {len(jobs)} runs ({preset.frames:,} frames each; "
            f"finished ones are reused, unfinished ones resume): about {hours:.1f} core-hours on a CPU"
        )


def run_table(
    spec: TableSpec,
    preset_name: str,
    runs_dir: Path | str = "runs",
    progress=print,
    workers: int = 1,
    device: str = "cpu",
    sources: Sources = Sources(),
    rows_named: tuple[str, ...] = (),
) -> TableResult:
    """Every row and seed (a job each), with progress and an ETA; resumable (see the module docstring).
    `rows_named`: only these rows of the preset (a partial table, its caption and file names say so).
    `workers` > 1 runs that many jobs at once in worker processes (torch on the preset's `threads`,
    else one thread, each). A job's options, threads among them, come from the spec alone, so with
    `threads` in the preset the runs and the table are the same whatever the number of workers; only
    the wall time differs."""
    preset = spec.preset(preset_name)
    if workers < 1:
        raise TableError(f"workers must be at least 1, got {workers}")
    runs_dir = Path(runs_dir)
    start = time.perf_counter()
    rows = only_rows(spec, preset, rows_named)
    jobs = [(row, seed) for row, seed in table_jobs(spec, preset) if row in rows]
    kinds = [_trains(row) for row, _ in jobs]
    if sources.train_only:  # only the jobs that train
        jobs = [job for job, trains in zip(jobs, kinds, strict=True) if trains]
        kinds = [True] * len(jobs)
    if sources.trained is None:
        announce_training(
            preset,
            [job for job, trains in zip(jobs, kinds, strict=True) if trains],
            runs_dir,
            device,
            progress,
        )
    outcomes: list[JobOutcome | None] = [None] * len(jobs)
    # torch's threads in every job, training (the option) and evaluation alike: the spec's, so that a
    # job's numbers do not depend on how many run at once (threads change the sums' order)
    threads = preset.threads
    done: list[tuple[bool, float]] = []

    def eta() -> str:
        left = time_left(done, [k for k, o in zip(kinds, outcomes, strict=True) if o is None])
        return f", about {left / 60 / workers:.0f} min left" if left is not None else ""

    def title(n: int) -> str:
        row, seed = jobs[n]
        return f"[{n + 1}/{len(jobs)}] {row.name} (seed {seed})"

    if workers == 1:
        for n, (row, seed) in enumerate(jobs):
            progress(f"== {title(n)}{eta()}")
            outcomes[n] = _job(spec, preset, row, seed, runs_dir, progress, threads, device, sources)
            if not outcomes[n].reused:
                done.append((kinds[n], outcomes[n].seconds))
    else:
        # spawn: a fresh interpreter per worker (torch's thread pools do not survive a fork); one
        # single-worker pool per job, `workers` at a time, so that a worker killed by a signal or the
        # OOM killer loses its own job only, named, while the others go on
        progress(f"== {len(jobs)} jobs, {workers} at a time, torch on one thread each")
        context = multiprocessing.get_context("spawn")
        # the longest first, so that the last job does not run alone: the rows further down the spec
        # add components (IL, TSE, the graph) and train slower
        queue = list(reversed(range(len(jobs))))
        running: dict[concurrent.futures.Future, tuple[int, concurrent.futures.Executor]] = {}
        lost: list[int] = []
        try:
            while queue or running:
                while queue and len(running) < workers:
                    n = queue.pop(0)
                    row, seed = jobs[n]
                    # a worker's lines, prefixed with its job (two jobs' lines interleave); picklable
                    prefix = functools.partial(print, f"{title(n)}:", flush=True)
                    pool = concurrent.futures.ProcessPoolExecutor(
                        1, mp_context=context, initializer=end_with_parent, initargs=(os.getpid(),)
                    )
                    job = (spec, preset, row, seed, runs_dir, prefix, threads or 1, device, sources)
                    running[pool.submit(_job, *job)] = (n, pool)
                finished, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in finished:
                    n, pool = running.pop(future)
                    pool.shutdown(wait=False)
                    try:
                        outcomes[n] = future.result()
                    except concurrent.futures.process.BrokenProcessPool:
                        lost.append(n)
                        progress(
                            f"== lost {title(n)}: its worker process died (a signal or the OOM killer); "
                            "the other jobs go on"
                        )
                        continue
                    if not outcomes[n].reused:
                        done.append((kinds[n], outcomes[n].seconds))
                    progress(f"== done {title(n)} in {outcomes[n].seconds / 60:.1f} min{eta()}")
        finally:
            for _, pool in running.values():
                pool.shutdown(wait=False, cancel_futures=True)
        if lost:
            names = "; ".join(title(n) for n in sorted(lost))
            raise TableError(
                f"{len(lost)} of {len(jobs)} jobs lost their worker process ({names}); the others are "
                "done: run the same command again to resume the lost ones and assemble the table"
            )
    per_row: dict[str, RowResult] = {}
    for (row, _), outcome in zip(jobs, outcomes, strict=True):
        result = per_row.setdefault(row.name, RowResult(row, [], [], [], 0.0))
        result.episodes.append(outcome.cells)
        result.train_runs.append(outcome.train_run)
        result.eval_runs.append(outcome.eval_run)
        result.seconds += outcome.seconds
    results = [per_row[row.name] for row in rows if row.name in per_row]  # (training only: trained rows)
    left_out = tuple(row.name for row in preset_rows(spec, preset) if row not in rows)
    return TableResult(spec, preset, results, time.perf_counter() - start, git_revision(), left_out)


# ------------------------------------------------------------------------------------------------
# Statistics: the cells' intervals and the comparisons' verdicts


@dataclass(frozen=True)
class CellStatistics:
    """One row's cell for one metric (SPL or SR), in percent."""

    seed_means: tuple[float | None, ...]  # each seed's episode mean; None: the seed has no episodes here
    episodes_per_seed: tuple[int, ...]
    bootstrap: Bootstrap | None  # None: no episodes in the cell
    interval: Interval | None  # the mean over seeds and its 95% interval


@dataclass(frozen=True)
class ComparisonStatistics:
    """One comparison in one cell for one metric: other - base, the paper's and ours, in points."""

    comparison: Comparison
    cell: str
    metric: str
    paper_base: float | None
    paper_other: float | None
    paper_difference: float | None  # None: the paper has the cell for one of the rows only, or neither
    ours: Interval | None  # None: one of the rows has no episodes in the cell
    verdict: str | None  # intervals.verdict; None where `ours` is None


@dataclass(frozen=True)
class TableStatistics:
    cells: dict[tuple[str, str, str], CellStatistics]  # (row name, "column/kind", metric)
    comparisons: list[ComparisonStatistics]


def bootstrap_seed(row_name: str, cell: str) -> tuple[int, int]:
    """Each row and cell its own random stream, named by the row's name (not its position: a row added
    or moved changes no other row's interval). Two rows' streams differ, so the bootstraps that a
    comparison differences are independent."""
    return zlib.crc32(row_name.encode()), CELL_KEYS.index(cell)


def paper_value(row: Row, cell: str, metric: str) -> float | None:
    pair = row.paper.get(cell)
    return None if pair is None else pair[METRICS.index(metric)]


def cell_statistics(row_result: RowResult, cell: str, reps: int = REPLICATES) -> dict[str, CellStatistics]:
    """A cell of a row, per metric: each seed's episode mean, and the mean over seeds with its 95%
    stratified bootstrap interval over the seeds that have episodes in the cell (all of them or none:
    every seed evaluates the same fixed episodes). SPL and SR come from the same resamples."""
    per_seed = [
        [(e.stratum, tuple(e.value(metric) for metric in METRICS)) for e in seed[cell]]
        for seed in row_result.episodes
    ]
    counts = tuple(len(episodes) for episodes in per_seed)
    present = [episodes for episodes in per_seed if episodes]
    boots = (
        joint_stratified_bootstrap(present, reps, bootstrap_seed(row_result.row.name, cell))
        if present
        else [None] * len(METRICS)
    )
    out = {}
    for m, (metric, boot) in enumerate(zip(METRICS, boots)):
        means = tuple(sum(values[m] for _, values in e) / len(e) if e else None for e in per_seed)
        out[metric] = CellStatistics(means, counts, boot, boot.interval() if boot else None)
    return out


def table_statistics(result: TableResult, reps: int = REPLICATES) -> TableStatistics:
    """Every row's cells and every comparison of the spec: a comparison's interval differences the two
    rows' own bootstrap replicates (independent streams), so it agrees with the cells it compares."""
    cells = {
        (r.row.name, cell, metric): statistics
        for r in result.rows
        for cell in CELL_KEYS
        for metric, statistics in cell_statistics(r, cell, reps).items()
    }
    rows = {r.row.name: r.row for r in result.rows}
    comparisons = []
    for comparison in result.spec.comparisons:
        if comparison.base not in rows or comparison.other not in rows:
            continue  # a result built without one of the rows (the spec checked the names)
        for cell in CELL_KEYS:
            for metric in METRICS:
                paper_base = paper_value(rows[comparison.base], cell, metric)
                paper_other = paper_value(rows[comparison.other], cell, metric)
                paper_difference = None
                if paper_base is not None and paper_other is not None:
                    # as printed, to the paper's 2 decimals (+ 0.0: no "-0.00")
                    paper_difference = round(paper_other - paper_base, 2) + 0.0
                base = cells[(comparison.base, cell, metric)].bootstrap
                other = cells[(comparison.other, cell, metric)].bootstrap
                ours = difference(base, other) if base is not None and other is not None else None
                comparisons.append(
                    ComparisonStatistics(
                        comparison,
                        cell,
                        metric,
                        paper_base,
                        paper_other,
                        paper_difference,
                        ours,
                        verdict(paper_difference, ours.low, ours.high) if ours else None,
                    )
                )
    return TableStatistics(cells, comparisons)


# ------------------------------------------------------------------------------------------------
# Writing the table

NONE = "–"  # no episodes in the cell, or not in the paper
NO_COMPARISON = "No comparison of the spec has both its rows in this table."


def _no_comparison_here(result: TableResult) -> bool:
    """The spec draws comparisons, but none has both its rows in this table (a partial one)."""
    return bool(result.spec.comparisons) and not result.statistics().comparisons


def interval_text(interval: Interval | None, signed: bool = False) -> str:
    """'52.6 [48.1, 57.0]' (a difference: '+4.1 [-0.3, +8.2]'); '–' for none."""
    if interval is None:
        return NONE
    f = "+.1f" if signed else ".1f"
    estimate, low, high = (x + 0.0 for x in (interval.estimate, interval.low, interval.high))  # no -0.0
    return f"{estimate:{f}} [{low:{f}}, {high:{f}}]"


def paper_text(value: float | None, signed: bool = False) -> str:
    """The paper's number as printed (2 decimals); '–' where it has none."""
    return NONE if value is None else f"{value:{'+.2f' if signed else '.2f'}}"


def _seeds_text(n: int) -> str:
    return f"{n} seed{'' if n == 1 else 's'}"


CHECKPOINT_TEXT = {
    "best_val_sr": (
        "the checkpoint with the best validation SR (ties to the later; FF A3C, whose scene-specific "
        "layers exist for its training kitchens only, validated on their seen targets from training "
        "starts that are no fixed episode's)"
    ),
    "last": "each run's final weights (last.pt), not the paper's rule of the best validation SR",
}


def caption(result: TableResult) -> str:
    p, pr = result.preset, result.spec.protocol
    rule = "Stop at the destination" if pr.success_rule == "destination" else "Stop with the target visible"
    stop = "Stop ends the episode" if pr.stop_ends else "a wrong Stop is a no-op"
    one_seed = " (one seed: the interval covers episodes only)" if p.seeds == 1 else ""
    some = p.unseen_target_kitchens
    unseen = f" (unseen targets in {len(some)} of the training kitchens: {', '.join(some)})" if some else ""
    return (
        f"Table I regenerated by kgnavbench, preset {p.name!r} ({p.description}): {p.frames:,} training "
        f"frames per learned row, {p.episodes} of the 100 fixed episodes per target, {_seeds_text(p.seeds)}; "
        f"success = {rule}, {stop}; caps {pr.seen_cap} (seen kitchens, seen targets) / {pr.unseen_cap}; "
        f"{CHECKPOINT_TEXT[checkpoint_rule(result.spec, p)]}. Cells: SPL and SR in %, ours as the mean over "
        f"{_seeds_text(p.seeds)}, 95% stratified bootstrap interval over seeds and episodes ({REPLICATES} "
        f"replicates){one_seed}; the paper's as printed on the line '(paper)'; seen/seen and seen/unseen: "
        f"seen kitchens with seen or unseen targets{unseen}; '–': no episodes in the cell, or none in the "
        f"paper. Git {result.git_revision}, wall time {result.seconds / 60:.1f} min."
        # "; ": a row's name may hold a comma ("+IL+TSE, object detections, no graph")
        + (f" Partial: without the preset's rows {'; '.join(result.left_out)}." if result.left_out else "")
    )


def _header() -> list[str]:
    return ["method"] + [f"{CELL_TITLES[cell]} {metric}" for cell in CELL_KEYS for metric in METRICS]


def table_rows(result: TableResult) -> list[list[str]]:
    """Two lines per row: ours (mean [95% interval]) and the paper's ('–' for a row that is ours)."""
    stats = result.statistics()
    lines = []
    for r in result.rows:
        name = r.row.name
        ours = [interval_text(stats.cells[(name, c, m)].interval) for c in CELL_KEYS for m in METRICS]
        paper = [paper_text(paper_value(r.row, c, m)) for c in CELL_KEYS for m in METRICS]
        lines += [[name, *ours], [f"{name} (paper)", *paper]]
    return lines


ABLATION_INTRO = (
    "For each comparison the paper draws and each cell: other − base in percentage points, the paper's "
    "(as printed) and ours (the difference of the two rows' means, with the 95% interval of the "
    "differences of their independent bootstrap replicates), and the verdict: holds (our interval lies "
    "on the paper's side of 0), reversed (on the other side), cannot tell (it contains 0); where the "
    "paper has no side (no difference printed, or one below 0.5 points), higher or lower (our interval "
    "lies above or below 0); '–': no episodes."
)


def _ablation_header() -> list[str]:
    head = ["comparison", "cell"]
    for metric in METRICS:
        head += [f"{metric} paper", f"{metric} ours", f"{metric} verdict"]
    return head


def ablation_rows(result: TableResult) -> list[list[str]]:
    """One line per comparison and cell: per metric the paper's difference, ours and the verdict."""
    by_key = {(s.comparison, s.cell, s.metric): s for s in result.statistics().comparisons}
    lines = []
    for comparison in result.spec.comparisons:
        for cell in CELL_KEYS:
            if (comparison, cell, METRICS[0]) not in by_key:
                continue
            line = [f"{comparison.other} − {comparison.base}", CELL_TITLES[cell]]
            for metric in METRICS:
                s = by_key[(comparison, cell, metric)]
                line += [
                    paper_text(s.paper_difference, signed=True),
                    interval_text(s.ours, signed=True),
                    s.verdict or NONE,
                ]
            lines.append(line)
    return lines


def verdict_counts(result: TableResult) -> str:
    """'SPL: holds 3, reversed 1, cannot tell 6; SR: ...' over every comparison and cell."""
    parts = []
    for metric in METRICS:
        verdicts = [s.verdict for s in result.statistics().comparisons if s.metric == metric and s.verdict]
        counts = ", ".join(f"{v} {verdicts.count(v)}" for v in VERDICTS)
        parts.append(f"{metric}: {counts}")
    return "; ".join(parts)


def _md_cell(text: str) -> str:
    """A markdown table cell: one line, its pipes escaped (a row named 'a | b' stays one cell)."""
    return one_line(text).replace("\\", "\\\\").replace("|", "\\|")


def _markdown_table(head: list[str], rows: list[list[str]], numeric: set[int]) -> list[str]:
    """A markdown table; the columns numbered in `numeric` right-aligned; every cell escaped."""
    align = "|" + "".join("---:|" if i in numeric else "---|" for i in range(len(head)))
    lines = ["| " + " | ".join(map(_md_cell, head)) + " |", align]
    return lines + ["| " + " | ".join(map(_md_cell, row)) + " |" for row in rows]


def to_markdown(result: TableResult) -> str:
    lines = [f"**{caption(result)}**", ""]
    head = _header()
    lines += _markdown_table(head, table_rows(result), numeric=set(range(1, len(head))))
    if _no_comparison_here(result):
        lines += ["", f"**Ablation check.** {NO_COMPARISON}"]
    elif result.spec.comparisons:
        lines += ["", f"**Ablation check.** {ABLATION_INTRO}", ""]
        head = _ablation_header()  # comparison, cell, then per metric: paper, ours, verdict
        numbers = {i for i in range(2, len(head)) if (i - 2) % 3 != 2}
        lines += _markdown_table(head, ablation_rows(result), numeric=numbers)
        lines += ["", f"Verdicts: {verdict_counts(result)}."]
    return "\n".join(lines) + "\n"


def _number(value: float | None) -> str:
    """A CSV number: 6 significant digits; empty for none (never NaN)."""
    return "" if value is None else f"{value + 0.0:.6g}"  # + 0.0: 0, never -0


def to_csv(result: TableResult) -> str:
    """Tidy: one line per row, cell and metric; each seed's own value in seed_0, seed_1, ..."""
    stats = result.statistics()
    seeds = max((len(r.episodes) for r in result.rows), default=0)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["# " + caption(result)])
    head = ["row", "method", "column", "kind", "metric", "mean", "ci_low", "ci_high", "paper"]
    writer.writerow(head + ["episodes_per_seed"] + [f"seed_{s}" for s in range(seeds)])
    for r in result.rows:
        for cell, (column, kind) in zip(CELL_KEYS, CELLS):
            for metric in METRICS:
                s = stats.cells[(r.row.name, cell, metric)]
                i = s.interval
                counts = sorted(set(s.episodes_per_seed))
                writer.writerow(
                    [r.row.name, r.row.method, column, kind, metric]
                    + [_number(i.estimate if i else None), _number(i.low if i else None)]
                    + [_number(i.high if i else None), _number(paper_value(r.row, cell, metric))]
                    # every seed runs the same episodes: one count (several, ';'-joined, would be a bug)
                    + [";".join(str(n) for n in counts)]
                    + [_number(m) for m in s.seed_means]
                    + [""] * (seeds - len(s.seed_means))
                )
    return out.getvalue()


def to_ablation_csv(result: TableResult) -> str:
    """Tidy: one line per comparison, cell and metric: the paper's two values and difference, ours with
    its 95% interval, the verdict (empty where we have no episodes)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    none = "" if result.statistics().comparisons else NO_COMPARISON + " "
    writer.writerow(["# Ablation check: " + none + ABLATION_INTRO + " " + caption(result)])
    writer.writerow(
        ["base", "other", "column", "kind", "metric", "paper_base", "paper_other", "paper_difference"]
        + ["difference", "ci_low", "ci_high", "verdict"]
    )
    for s in result.statistics().comparisons:
        column, _, kind = s.cell.partition("/")
        i = s.ours
        writer.writerow(
            [s.comparison.base, s.comparison.other, column, kind, s.metric]
            + [_number(s.paper_base), _number(s.paper_other), _number(s.paper_difference)]
            + [_number(i.estimate if i else None), _number(i.low if i else None)]
            + [_number(i.high if i else None), s.verdict or ""]
        )
    return out.getvalue()


TEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "_": r"\_",
    "#": r"\#",
    "$": r"\$",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def _tex_escape(text: str) -> str:
    """A LaTeX table cell: LaTeX's special characters escaped in one pass, on one line."""
    text = "".join(TEX_SPECIAL.get(ch, ch) for ch in one_line(text))
    if not any(ch.isalpha() for ch in text):
        text = text.replace("-", "$-$")  # a number's minus sign, not a hyphen
    return text.replace("−", "$-$").replace("–", "--")


def _tex_tabular(spec: str, head: list[str], rows: list[list[str]]) -> list[str]:
    lines = [r"\resizebox{\textwidth}{!}{%", r"\begin{tabular}{" + spec + "}", r"\hline"]
    lines += head + [r"\hline"]
    lines += [" & ".join(_tex_escape(c) for c in row) + r" \\" for row in rows]
    return lines + [r"\hline", r"\end{tabular}}"]


def to_latex(result: TableResult) -> str:
    """Table I with intervals and the paper's numbers, then the ablation check (needs graphicx)."""
    kinds = [("static", 3), ("actionable", 2)]  # CELLS: three static cells, then two actionable
    groups = " & ".join(rf"\multicolumn{{{2 * n}}}{{c}}{{{kind} targets}}" for kind, n in kinds)
    columns = " & ".join(rf"\multicolumn{{2}}{{c}}{{{COLUMN_TITLES[column]}}}" for column, _ in CELLS)
    head = [rf" & {groups} \\", rf" & {columns} \\", " & " + " & ".join(["SPL & SR"] * len(CELLS)) + r" \\"]
    lines = [
        "% needs \\usepackage{graphicx} (\\resizebox)",
        r"\begin{table*}",
        r"\centering",
        r"\caption{" + _tex_escape(caption(result)) + "}",
    ]
    lines += _tex_tabular("l" + "rr" * len(CELLS), head, table_rows(result))
    lines.append(r"\end{table*}")
    if _no_comparison_here(result):
        lines.append("% Ablation check. " + NO_COMPARISON)
    elif result.spec.comparisons:
        metrics = " & ".join(rf"\multicolumn{{3}}{{c}}{{{metric}}}" for metric in METRICS)
        head = [
            rf" & & {metrics} \\",
            "comparison & cell & " + " & ".join(["paper & ours & verdict"] * len(METRICS)) + r" \\",
        ]
        lines += [
            r"\begin{table*}",
            r"\centering",
            r"\caption{Ablation check. " + _tex_escape(ABLATION_INTRO) + "}",
        ]
        lines += _tex_tabular("ll" + "rrl" * len(METRICS), head, ablation_rows(result))
        lines.append(r"\end{table*}")
    return "\n".join(lines) + "\n"


def write_table(result: TableResult, out_dir: Path | str) -> list[Path]:
    """tables/table1.{md,csv,tex} and table1-ablation.csv for the quick preset, table1-<preset>.* and
    table1-<preset>-ablation.csv for the others; `-partial` after the preset's name for a table without
    some of its rows (`--row`), so that it never overwrites the whole one (a later partial table of the
    same preset replaces an earlier one)."""
    out_dir = Path(out_dir)
    stem = "table1" if result.preset.name == "quick" else f"table1-{result.preset.name}"
    stem += "-partial" if result.left_out else ""
    paths = []
    for name, text in (
        (f"{stem}.md", to_markdown(result)),
        (f"{stem}.csv", to_csv(result)),
        (f"{stem}-ablation.csv", to_ablation_csv(result)),
        (f"{stem}.tex", to_latex(result)),
    ):
        path = out_dir / name
        try:
            atomic_write(path, text)
        except OSError as e:
            raise TableError(f"cannot write {path}: {e.strerror or e}") from e
        paths.append(path)
    return paths
