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
import dataclasses
import functools
import json
import multiprocessing
import os
import time
from dataclasses import dataclass
from pathlib import Path
from shlex import quote
from typing import NamedTuple

import torch

from .device import DeviceError, name_of, resolve
from .evaluate import (
    EvalConfig,
    EvalRun,
    evaluate,
    scored_visible,
)
from .files import atomic_write, end_with_parent, one_line
from .kitchens import KITCHEN_NAMES
from .plugins import PluginError, load_plugin
from .runs import (
    TrainError,
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
    # spawn: a fresh interpreter per worker (torch's thread pools do not survive a fork); `workers`
    # single-worker pools, so that a worker killed by a signal or the OOM killer loses its own job
    # only, named, while the others go on. A pool whose job ended takes the next one: its interpreter
    # has paid for the imports (about 3 s each) and a job depends on nothing its process did before,
    # as with `workers` = 1, where one process runs them all
    progress(f"== {len(jobs)} jobs, {workers} at a time, torch on one thread each")
    context = multiprocessing.get_context("spawn")
    # the longest first, so that the last job does not run alone: the rows further down the spec
    # add components (IL, TSE, the graph) and train slower
    queue = list(reversed(range(len(jobs))))
    running: dict[concurrent.futures.Future, tuple[int, concurrent.futures.Executor]] = {}
    idle: list[concurrent.futures.Executor] = []
    lost: list[int] = []

    def submit(n: int) -> None:
        # a worker's lines, prefixed with its job (two jobs' lines interleave); picklable
        prefix = functools.partial(print, f"{title(n)}:", flush=True)
        job = dataclasses.replace(jobs[n], threads=jobs[n].threads or 1)
        while idle:  # an idle pool whose worker died after its last job is broken: dropped
            pool = idle.pop()
            try:
                running[pool.submit(execute, job, prefix)] = (n, pool)
                return
            except (concurrent.futures.process.BrokenProcessPool, RuntimeError):
                pool.shutdown(wait=False)
        pool = concurrent.futures.ProcessPoolExecutor(
            1, mp_context=context, initializer=end_with_parent, initargs=(os.getpid(),)
        )
        running[pool.submit(execute, job, prefix)] = (n, pool)

    try:
        while queue or running:
            while queue and len(running) < workers:
                submit(queue.pop(0))
            while idle and not queue:  # nothing left for them: their interpreters end now
                idle.pop().shutdown(wait=False)
            finished, _ = concurrent.futures.wait(running, return_when=concurrent.futures.FIRST_COMPLETED)
            for future in finished:
                n, pool = running.pop(future)
                idle.append(pool)
                try:
                    outcomes[n] = future.result()
                except concurrent.futures.process.BrokenProcessPool:
                    idle.remove(pool)
                    pool.shutdown(wait=False)
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
        for pool in [pool for _, pool in running.values()] + idle:
            pool.shutdown(wait=False, cancel_futures=True)
    if lost:
        names = "; ".join(title(n) for n in sorted(lost))
        raise TableError(
            f"{len(lost)} of {len(jobs)} jobs lost their worker process ({names}); the others are "
            "done: run the same command again to resume the lost ones and assemble the table"
        )
    return outcomes
