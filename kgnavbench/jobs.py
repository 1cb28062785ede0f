"""Stage 28 — jobs: a table's jobs (one row for one seed each) and the engines that run them.

A `Job` trains (or finds, or resumes) one row's run for one seed and evaluates its checkpoint under the
preset's rule (`run_row`); `execute` runs it in this process and keeps what the table needs
(`JobOutcome`). The engines: `run_jobs` in this process or in worker processes on this machine;
`job_commands` and `run_job` (`table --jobs`, `--job N`) for Slurm arrays, xargs or ssh loops, each job
one command into a shared runs folder; `run_jobs_on_ray` (`table --ray ADDRESS`) every job as a task on a
Ray cluster whose nodes share the runs folder, retried where a node dies. Every job is a resumable run
directory, so a job run twice, or killed and run again, continues where it stopped.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import json
import multiprocessing
import os
import platform
import shlex
import shutil
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from shlex import quote
from typing import NamedTuple

import torch

from . import claims
from .device import DeviceError, name_of, resolve
from .evaluate import (
    EvalConfig,
    EvalRun,
    evaluate,
    scored_visible,
)
from .files import NUMERICS_ENV, atomic_write, end_with_parent, first_line, git_revision, one_line
from .kitchens import KITCHEN_NAMES
from .plugins import PluginError, load_plugin
from .runs import (
    TrainError,
    imported_training_code_sha256,
    load_checkpoint,
    run_directory,
    run_record,
    train_method,
    training_kitchens,
)
from .table_spec import (
    SPEC_FILE,
    Preset,
    Row,
    TableError,
    TableSpec,
)
from .table_statistics import EpisodeValue, cell_episodes
from .tasks import load_task_file
from .zoo import RUN_FOLDER, record_differences, trained_run


@dataclass(frozen=True)
class Sources:
    """Where a job's trained run comes from and what the job does with it: by default it trains (or
    finds, or resumes) the run in the runs folder and evaluates it. `trained`: take the finished run
    from that folder instead (a zoo of shipped runs, or another runs folder) and never train.
    `train_only`: train, and leave evaluating and assembling to a later `table`. `archive`: a folder of
    packed evaluations (tables/episodes/paper): a job's evaluation kept there is unpacked into the runs
    folder and counted, not run again, and one it runs is packed there when it finishes."""

    trained: Path | None = None
    train_only: bool = False
    archive: Path | None = None


@dataclass(frozen=True, kw_only=True)
class Job:
    """One row of a preset for one seed: trained (or found, or resumed) and evaluated into `runs_dir`,
    on `device`, from `sources`; torch on `threads` threads in its process (0: torch's own number).
    Picklable, so that any engine (this process, a worker process, a Ray task) runs the same value."""

    spec: TableSpec
    preset: Preset
    row: Row
    seed: int
    runs_dir: Path
    device: str = "cpu"
    sources: Sources = Sources()
    threads: int = 0

    def title(self, number: int, total: int) -> str:
        """ "[3/27] IL (seed 2)": the job's place in its table, its row and seed."""
        return f"[{number}/{total}] {self.row.name} (seed {self.seed})"


def checkpoint_rule(spec: TableSpec, preset: Preset) -> str:
    """The checkpoint rule a preset's evaluations follow: its own, else the protocol's."""
    return preset.checkpoint or spec.protocol.checkpoint


def preset_rows(spec: TableSpec, preset: Preset) -> list[Row]:
    return [row for row in spec.rows if not preset.rows or row.name in preset.rows]


def table_jobs(spec: TableSpec, preset: Preset) -> list[tuple[Row, int]]:
    """The preset's jobs, (row, seed) each, in the table's order: job N (from 1) is the N-th. Every row's
    seeds below the preset's `seeds` come first, row by row; the seeds a row has beyond them (its
    `row_seeds`) follow, row by row. Raising a row's seeds renumbers no job of the first part, but may
    renumber the extra seeds of later rows: job numbers belong to one version of the spec (`--jobs`
    prints them)."""
    rows = preset_rows(spec, preset)
    first = [(row, s) for row in rows for s in range(min(preset.seeds, preset.seeds_of(row.name)))]
    extra = [(row, s) for row in rows for s in range(preset.seeds, preset.seeds_of(row.name))]
    return first + extra


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


def find_trained(
    preset: Preset,
    row: Row,
    seed: int,
    options: dict,
    folder: Path,
    device: str,
    progress=print,
    unfinished: bool = False,
) -> Path:
    """The finished run in `folder` (a zoo, or a runs folder; `unfinished`: or the one still training)
    that trained this row's job as the preset says (`trained_run`), whatever code revision trained it."""
    plugin = load_plugin(row.method)
    try:
        on = name_of(resolve(device))
    except DeviceError as e:
        raise TableError(str(e)) from e
    record = run_record(
        plugin, plugin.config(options), preset.frames, seed, training_kitchens(preset.train_kitchens), on
    )
    return trained_run(folder, record, row.name, progress, unfinished)


# zoo/README.md's listing sits between these lines; `kgnavbench ship` rewrites it (`write_zoo_listing`)
ZOO_LISTING_START = (
    "<!-- the listing below is written by `kgnavbench ship` from the folders here; do not edit -->"
)
ZOO_LISTING_END = "<!-- end of the listing -->"


def zoo_listing(zoo: Path, spec: TableSpec) -> str:
    """The markdown table of the runs in `zoo`, read from their own files: for each run folder, the
    spec's row whose job it is (matched on TRAINED_RUN_KEYS, as `table --trained` matches) and the
    presets that have that row, its seed, the frames it trained and those of best.pt, and whether it
    ships last.pt. Runs in the spec's row order, then seed; a run of no row last, with the closest row
    and what it differs in."""
    plugins, wanted = {}, {}  # method -> plugin; (preset, row, seed, device, world) -> the job's keys

    def job(preset: Preset, row: Row, config: dict) -> dict:
        key = (preset.name, row.name, config.get("seed"), config.get("device"), config.get("world_size"))
        if key not in wanted:
            plugin = plugins.setdefault(row.method, load_plugin(row.method))
            kitchens = training_kitchens(preset.train_kitchens)
            # the job's record as the trainer builds it, on the run's own ranks and device
            record = run_record(plugin, plugin.config(row_options(preset, row)), preset.frames, 0, kitchens)
            wanted[key] = record | {k: config.get(k) for k in ("seed", "world_size", "device")}
        return wanted[key]

    lines = []
    for folder in sorted(p for p in zoo.iterdir() if p.is_dir() and RUN_FOLDER.fullmatch(p.name)):
        config = json.loads((folder / "config.json").read_text())
        finished = json.loads((folder / "finished.json").read_text())
        found, closest = {}, None  # row order -> (row, its presets), (differences, row, what differs)
        for order, row in enumerate(spec.rows):
            if row.method != config.get("method") or not trains(row):
                continue
            for preset in spec.presets.values():
                differ = record_differences(config, job(preset, row, config))
                if not differ:
                    presets = found.setdefault(order, (row, []))[1]
                    if row.name in preset.rows or not preset.rows:
                        presets.append(preset.name)
                elif closest is None or len(differ) < closest[0]:
                    closest = (len(differ), row.name, ", ".join(differ[:3]))
        if found:
            row_order = min(found)
            name, presets = found[row_order][0].name, ", ".join(found[row_order][1]) or "none"
        else:
            row_order, presets = len(spec.rows), "none"
            name = f"none (closest: {closest[1]}; differs in {closest[2]})" if closest else "none"
        best = load_checkpoint(folder / "best.pt")["frames"]
        last = "yes" if (folder / "last.pt").is_file() else "no"
        cells = f"| `{folder.name}` | {name} | {presets} | {config['seed']} | {finished['frames']:,} | "
        cells += f"{best:,} | {last} |"
        lines.append(((row_order, config["seed"], folder.name), cells))
    head = "| run | row | presets | seed | frames | best.pt from | last.pt |\n"
    return head + "|---|---|---|---:|---:|---:|---|\n" + "".join(cells + "\n" for _, cells in sorted(lines))


def write_zoo_listing(zoo: Path, spec: TableSpec) -> bool:
    """Rewrite the listing in `zoo`/README.md (between ZOO_LISTING_START and _END); False where the
    README has no listing (a zoo of your own)."""
    readme = zoo / "README.md"
    text = readme.read_text() if readme.is_file() else ""
    if ZOO_LISTING_START not in text or ZOO_LISTING_END not in text:
        return False
    head, rest = text.split(ZOO_LISTING_START, 1)
    _, tail = rest.split(ZOO_LISTING_END, 1)
    atomic_write(
        readme, f"{head}{ZOO_LISTING_START}\n{zoo_listing(zoo, spec)}{ZOO_LISTING_END}{tail}".encode()
    )
    return True


def eval_config(
    spec: TableSpec,
    preset: Preset,
    row: Row,
    *,
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


def trains(row: Row) -> bool:
    try:
        return callable(getattr(load_plugin(row.method).module, "train", None))
    except PluginError as e:
        raise TableError(f"row {row.name!r}: {e}") from e


def row_options(preset: Preset, row: Row) -> dict:
    """A row's options: a learned row's are the preset's with the row's over them."""
    return {**preset.options, **row.options} if trains(row) else dict(row.options)


def run_row(job: Job, progress=print) -> tuple:
    """Train (or find, or resume) one row's run for one seed, then evaluate its checkpoint under the
    preset's rule (the eval run is None under `sources.train_only`)."""
    spec, preset, row, seed, sources = job.spec, job.preset, job.row, job.seed, job.sources
    options = row_options(preset, row)
    run_dir = None
    if trains(row):
        if sources.trained is not None:
            run_dir = find_trained(preset, row, seed, options, sources.trained, job.device, progress)
        else:
            run_dir = train_method(
                row.method,
                options,
                preset.frames,
                seed,
                preset.train_kitchens,
                job.runs_dir,
                progress=progress,
                device=job.device,
            )
    if sources.train_only:
        return run_dir, None
    config = eval_config(spec, preset, row, seed=seed, options=options, run_dir=run_dir, device=job.device)
    if not config.kitchens:  # every evaluation kitchen is an unseen one, where this row has no cells: "–"
        return run_dir, EvalRun(config, Path(job.runs_dir) / "eval")  # (no kitchens would mean all of them)
    return run_dir, evaluate(config, job.runs_dir, progress=progress, archive=sources.archive)


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


def execute(job: Job, progress=print) -> JobOutcome:
    """One job, in this process: what the table keeps of it. Called in the table's process, in a worker
    process or in a Ray task (with `job.threads` torch threads: 1 where jobs run side by side, so that
    they do not wait on each other's cores; set here, in the process that computes)."""
    threads, sources, row = job.threads, job.sources, job.row
    if threads:
        torch.set_num_threads(threads)
    started = time.time()
    t0 = time.perf_counter()
    try:
        run_dir, run = run_row(job, progress)
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
    results = run.results if run is not None else []
    if job.preset.score_rule == "visible" and job.spec.protocol.success_rule != "visible":
        results = scored_visible(results)  # the same evaluations, scored under the visible rule
    return JobOutcome(
        cell_episodes(results) if run is not None else {},
        str(run_dir) if run_dir else "",
        str(run.directory) if run is not None else "",
        time.perf_counter() - t0,
        reused,
    )


def job_commands(
    spec: TableSpec, preset_name: str, runs_dir: Path | str, sources: Sources = Sources()
) -> list[str]:
    """One shell command per job (for a Slurm array, `xargs -P`, ssh loops): each trains and evaluates
    its row and seed into the shared runs folder (as `sources` says: --trained, --train-only and
    --archive carry over); `kgnavbench table` after them only assembles."""
    preset = spec.preset(preset_name)
    jobs = table_jobs(spec, preset)
    spec_option = (
        "" if Path(spec.path).resolve() == SPEC_FILE.resolve() else f" --spec {quote(str(spec.path))}"
    )
    base = f"kgnavbench table --preset {quote(preset.name)}{spec_option} --runs {quote(str(runs_dir))}"
    base += f" --trained {quote(str(sources.trained))}" if sources.trained is not None else ""
    base += " --train-only" if sources.train_only else ""
    base += f" --archive {quote(str(sources.archive))}" if sources.archive is not None else ""
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
    if sources.trained is None and trains(row):  # a run trained by other code is not this one
        announce_training(preset, [(row, seed)], Path(runs_dir), device, progress)
    job = Job(
        spec=spec, preset=preset, row=row, seed=seed, runs_dir=Path(runs_dir), device=device, sources=sources,
        threads=preset.threads,
    )  # fmt: skip
    execute(job, progress)


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


def run_jobs(jobs: list[Job], progress=print, workers: int = 1) -> list[JobOutcome]:
    """Every job, with progress and an ETA, in this process (`workers` = 1) or `workers` at a time in
    worker processes; the outcomes in the jobs' order. A job's options, threads among them, come from
    the spec alone, so the runs are the same whatever the number of workers; only the wall time
    differs. A worker killed by a signal loses its own job only: the others finish, then a TableError
    names the lost ones."""
    if workers < 1:
        raise TableError(f"workers must be at least 1, got {workers}")
    kinds = [trains(job.row) for job in jobs]
    outcomes: list[JobOutcome | None] = [None] * len(jobs)
    done: list[tuple[bool, float]] = []

    def eta() -> str:
        left = time_left(done, [k for k, o in zip(kinds, outcomes, strict=True) if o is None])
        return f", about {left / 60 / workers:.0f} min left" if left is not None else ""

    def title(n: int) -> str:
        return jobs[n].title(n + 1, len(jobs))

    if workers == 1:
        for n, job in enumerate(jobs):
            progress(f"== {title(n)}{eta()}")
            outcomes[n] = execute(job, progress)
            if not outcomes[n].reused:
                done.append((kinds[n], outcomes[n].seconds))
        return outcomes
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
                # a worker's lines, prefixed with its job (two jobs' lines interleave); picklable
                prefix = functools.partial(print, f"{title(n)}:", flush=True)
                pool = concurrent.futures.ProcessPoolExecutor(
                    1, mp_context=context, initializer=end_with_parent, initargs=(os.getpid(),)
                )
                job = dataclasses.replace(jobs[n], threads=jobs[n].threads or 1)
                running[pool.submit(execute, job, prefix)] = (n, pool)
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
    return outcomes


# A Ray task whose worker process or node dies runs again, this many times at most; the trainer resumes
# from the run's last.pt, so a retry continues its run. The job's own errors are not retried.
RAY_RETRIES = 3
RAY_STATUS_EVERY = 60.0  # seconds between the driver's status lines while nothing ends
# what a job's process must see as the driver does, whatever environment the nodes were started in:
# the state-graph cache and the vector code paths that decide a run's floats (files.NUMERICS_ENV, which
# every run directory records, less the thread count: each job sets its own from the preset's `threads`)
RAY_ENV = ("KGNAVBENCH_CACHE", *(name for name in NUMERICS_ENV if name != "OMP_NUM_THREADS"))


def _ray_task(job: Job, title: str, attempts: str, cwd: str) -> JobOutcome:
    """One job in a Ray worker process, in the driver's working directory `cwd` (a shared folder: the
    runs folder, the spec and a researcher's ./baselines are found as the driver finds them). Its claims
    record its node, and a claim left by a node Ray reports dead is taken over (a retry of this job on
    another node resumes its run); each attempt adds a line to `attempts`, from which the driver tells
    a retry."""
    import ray

    try:
        os.chdir(cwd)
    except OSError as e:
        raise TableError(
            f"{title}: the driver's working directory {cwd} is not on {socket.gethostname()} "
            f"({e.strerror}); run the table from a folder that every node shares, at the same path"
        ) from e
    node = ray.get_runtime_context().get_node_id()
    nodes = ray.nodes()
    claims.on_cluster(
        node,
        [n["NodeID"] for n in nodes if not n["Alive"]],
        [n["NodeID"] for n in nodes],
        ray.get_runtime_context().gcs_address,
    )
    with open(attempts, "a") as f:
        record = {"node": node, "host": socket.gethostname(), "pid": os.getpid(), "since": time.time()}
        f.write(json.dumps(record) + "\n")
    return execute(job, functools.partial(print, f"{title}:", flush=True))


def _attempts(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.is_file() else 0


def _check_ray_port(address: str, seconds: float = 5.0) -> None:
    """A HOST:PORT address that nothing answers at is named at once (ray.init would wait minutes, then
    fail with a page of its logs); "auto" and ray:// addresses are left to Ray."""
    host, sep, port = address.rpartition(":")
    if address == "auto" or "://" in address or not sep or not port.isdigit():
        return
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=seconds):
            pass
    except OSError as e:
        raise TableError(
            f"--ray {address}: nothing answers there ({e.strerror or type(e).__name__}); start a cluster "
            "with `ray start --head` (docs/scaling.md), or pass --ray auto on one of its nodes"
        ) from e


def node_environment() -> dict[str, str]:
    """What must be the same on every node as on the driver, or a job's floats (or its code) are not
    the table's: Python's version, torch's, kgnavbench's revision (files.git_revision) and the sha256
    of its training code as imported (a pip install outside a checkout has no revision; a "-dirty"
    one says nothing of which edits)."""
    return {
        "Python": platform.python_version(),
        "torch": torch.__version__,
        "kgnavbench": git_revision(),
        "training code": imported_training_code_sha256()[:12],
    }


def environment_problems(driver: dict[str, str], nodes: dict[str, dict[str, str]]) -> str | None:
    """One sentence naming the first node (by name) whose `node_environment` differs from the driver's
    and how; None when every node's is the driver's."""
    for name, theirs in sorted(nodes.items()):
        differ = [
            f"{k} {theirs.get(k, '(none)')} (here {v})" for k, v in driver.items() if theirs.get(k) != v
        ]
        if differ:
            return f"node {name} runs {', '.join(differ)}"
    return None


RAY_PROBE_SECONDS = 25.0  # how long the driver waits for every node's environment


def _check_ray_nodes(ray, address: str, head: str) -> None:
    """Ask every live node that can run a job (one with a CPU), in a task pinned to it that takes no
    CPU (so a busy node answers too), for its `node_environment`; a node that differs from the
    driver's, fails, or does not answer in RAY_PROBE_SECONDS is named in a TableError. (A node that
    joins later is not asked.)"""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    nodes = [n for n in ray.nodes() if n["Alive"] and n.get("Resources", {}).get("CPU", 0) > 0]
    probe = ray.remote(num_cpus=0, max_retries=0)(node_environment)
    refs = [
        probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(n["NodeID"], soft=False)).remote()
        for n in nodes
    ]

    def name(n: dict) -> str:
        return f"{n.get('NodeManagerHostname', '?')} ({n['NodeManagerAddress']}, {n['NodeID'][:8]})"

    ready, _ = ray.wait(refs, num_returns=len(refs), timeout=RAY_PROBE_SECONDS)
    reports = {}
    for n, ref in zip(nodes, refs):
        if ref not in ready:
            raise TableError(
                f"--ray {address}: node {name(n)} of the cluster at {head} did not say what it runs within "
                f"{RAY_PROBE_SECONDS:.0f} s; check `ray status`"
            )
        try:
            reports[name(n)] = ray.get(ref)
        except Exception as e:  # noqa: BLE001 - whatever the node raised (kgnavbench missing there, ...)
            raise TableError(
                f"--ray {address}: node {name(n)} cannot run kgnavbench ({type(e).__name__}: {first_line(e)})"
            ) from e
    problem = environment_problems(node_environment(), reports)
    if problem:
        raise TableError(
            f"--ray {address}: {problem}; every node needs the driver's Python, torch and kgnavbench "
            "(the same install and commit, docs/scaling.md)"
        )


RAY_HEAD_LOST_AFTER = 30.0  # seconds without an answer from the head: the cluster is lost (Ray waits 60)


def _watch_head(
    head: str, command: str, every: float = 5.0, lost_after: float = RAY_HEAD_LOST_AFTER, lost=None
) -> threading.Event:
    """A thread that connects to the head's port every `every` seconds; if it has not answered for
    `lost_after`, the driver ends with one line naming what was lost and the command that resumes
    (`lost`, for a test, is called with that line instead of ending the process). Set the returned
    event to stop it."""
    stop = threading.Event()

    def end(line: str) -> None:
        print(line, file=sys.stderr, flush=True)
        os._exit(2)  # Ray's own threads would otherwise wait out their 60 s and print a page

    def watch() -> None:
        silent_since = None
        while not stop.wait(every):
            if claims.answers(head, min(every, 3.0)):
                silent_since = None
            else:
                silent_since = silent_since or time.monotonic()
                if time.monotonic() - silent_since >= lost_after:
                    (lost or end)(
                        f"kgnavbench: error: lost the Ray cluster's head at {head} (no answer for "
                        f"{lost_after:.0f} s); the finished jobs and every run's last checkpoint are saved: "
                        f"start a cluster and run `{command}` again to resume"
                    )
                    return

    threading.Thread(target=watch, name="kgnavbench-ray-head", daemon=True).start()
    return stop


def run_jobs_on_ray(
    jobs: list[Job], address: str, progress=print, node_ip: str | None = None
) -> list[JobOutcome]:
    """Every job as a Ray task on the cluster at `address` (as `ray.init` takes it, "auto" included),
    each with the CPUs of its torch threads; the outcomes in the jobs' order. Each task runs in the
    driver's working directory, which, with the runs folder, must be the same path on every node (a
    shared file system): Ray moves no files. A task whose worker or
    node dies is retried (RAY_RETRIES); a job's own error is not, and is named when the others have
    ended. While jobs run, the driver prints which are running, done, retried or failed, with an ETA.
    `node_ip`: this machine's address on the cluster, where Ray would guess another (a loopback one)."""
    try:
        import ray
        from ray.exceptions import RayError, RayTaskError
    except ImportError as e:
        raise TableError("--ray needs Ray, an optional extra: pip install 'kgnavbench[ray]'") from e
    if not jobs:
        return []
    _check_ray_port(address)
    env = {name: os.environ[name] for name in RAY_ENV if name in os.environ}
    try:
        ray.init(
            address=address,
            _node_ip_address=node_ip,
            runtime_env={"env_vars": env} if env else None,
            log_to_driver=True,
            logging_level="WARNING",
        )
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise TableError(f"--ray {address}: cannot reach a Ray cluster there ({first_line(e)})") from e
    head = ray.get_runtime_context().gcs_address
    cpus = int(ray.cluster_resources().get("CPU", 0))
    needs = min(job.threads or 1 for job in jobs)
    if cpus < needs:  # Ray would wait forever for a node that can run a task
        ray.shutdown()
        raise TableError(
            f"--ray {address}: the cluster at {head} has {cpus} CPUs and a job needs {needs}; start its "
            "nodes with CPUs (`ray start ... --num-cpus=N`, N >= 1)"
        )
    try:
        _check_ray_nodes(ray, address, head)
    except BaseException:
        ray.shutdown()
        raise
    watchdog = _watch_head(head, shlex.join(["kgnavbench", *sys.argv[1:]]))
    runs_dir = Path(jobs[0].runs_dir)
    attempts_dir = runs_dir / "ray" / f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    attempts_dir.mkdir(parents=True)
    kinds = [trains(job.row) for job in jobs]
    outcomes: list[JobOutcome | None] = [None] * len(jobs)
    failed: dict[int, str] = {}
    done: list[tuple[bool, float]] = []

    def title(n: int) -> str:
        return jobs[n].title(n + 1, len(jobs))

    def attempts_file(n: int) -> Path:
        return (attempts_dir / f"job-{n + 1:03d}").resolve()

    def status(parallel: int) -> str:
        counts = [_attempts(attempts_file(n)) for n in range(len(jobs))]  # each file read once
        started = [n for n, count in enumerate(counts) if count]
        retried = [n for n, count in enumerate(counts) if count > 1]
        ended = {n for n, o in enumerate(outcomes) if o is not None} | set(failed)
        running = [n for n in started if n not in ended]
        left = time_left(done, [k for n, k in enumerate(kinds) if n not in ended])
        eta = f", about {left / 60 / parallel:.0f} min left" if left is not None else ""
        return (
            f"== ray: {len(running)} running, {len(ended) - len(failed)} done, {len(retried)} retried, "
            f"{len(failed)} failed, {len(jobs) - len(ended) - len(running)} waiting{eta}"
        )

    try:
        task = ray.remote(_ray_task)
        refs = {}
        for n, job in enumerate(jobs):
            job = dataclasses.replace(job, threads=job.threads or 1)
            options = dict(num_cpus=job.threads, max_retries=RAY_RETRIES, retry_exceptions=False)
            attempts = str(attempts_file(n))
            remote = task.options(name=title(n), **options)
            refs[remote.remote(job, title(n), attempts, os.getcwd())] = n
        parallel = max(1, cpus // max(job.threads or 1 for job in jobs))
        joined = f"{address} (head {head})" if address != head else address  # "auto": the one it joined
        progress(f"== {len(jobs)} jobs on the Ray cluster at {joined} ({cpus} CPUs)")
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1, timeout=RAY_STATUS_EVERY)
            for ref in ready:
                n = refs[ref]
                try:
                    outcomes[n] = ray.get(ref)
                except RayTaskError as e:  # the job's own error (its traceback went to the log above)
                    cause = e.cause if e.cause is not None else e
                    failed[n] = f"{type(cause).__name__}: {first_line(cause)}"
                    progress(f"== failed {title(n)}: {failed[n]}")
                    continue
                except RayError as e:  # its worker or node died, more times than it is retried
                    failed[n] = f"lost after {RAY_RETRIES} retries ({type(e).__name__}: {first_line(e)})"
                    progress(f"== failed {title(n)}: {failed[n]}")
                    continue
                if not outcomes[n].reused:
                    done.append((kinds[n], outcomes[n].seconds))
                progress(f"== done {title(n)} in {outcomes[n].seconds / 60:.1f} min")
            progress(status(parallel))
    finally:
        watchdog.set()
        ray.shutdown()
        shutil.rmtree(attempts_dir, ignore_errors=True)
        with contextlib.suppress(OSError):  # runs/ray, unless another driver keeps its attempts there
            attempts_dir.parent.rmdir()
    if failed:
        names = "; ".join(f"{title(n)}: {why}" for n, why in sorted(failed.items()))
        raise TableError(
            f"{len(failed)} of {len(jobs)} jobs failed ({names}); the others are done: fix the cause and "
            "run the same command again to resume"
        )
    return outcomes
