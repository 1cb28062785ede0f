"""Stage 31 — table: the paper's Table I from a table spec (`tables/table1.toml`), run and assembled.

The spec (kgnavbench/table_spec.py) names the protocol, the presets, the rows and the comparisons
the paper draws between rows. `run_table` runs every row and seed (`jobs`): train unless a finished
run with the same config exists (an unfinished one resumes), take the checkpoint the preset's rule
picks, evaluate it on the fixed episodes (per-episode JSON lines in the eval run). It then assembles
the rows into a `TableResult` (`table_statistics`), which kgnavbench/table_files.py writes as
markdown, CSV and LaTeX. Everything it runs is a resumable run directory, so a killed `make table`
continues where it stopped. The table's other two jobs have their own stages: the paired tables of
two presets (kgnavbench/table_paired.py) and the verdicts of written tables recomputed
(kgnavbench/reverdict.py).
"""

from __future__ import annotations

import time
from pathlib import Path

from .files import git_revision
from .jobs import (
    Job,
    Sources,
    announce_training,
    only_rows,
    preset_rows,
    run_jobs,
    table_jobs,
    trains,
)
from .ray_jobs import run_jobs_on_ray
from .table_spec import (
    TableError,
    TableSpec,
)
from .table_statistics import RowResult, TableResult
from .zoo import other_code_runs


def run_table(
    spec: TableSpec,
    preset_name: str,
    runs_dir: Path | str = "runs",
    *,
    progress=print,
    workers: int = 1,
    device: str = "cpu",
    sources: Sources | None = None,
    rows_named: tuple[str, ...] = (),
    ray_address: str | None = None,
    ray_node_ip: str | None = None,
) -> TableResult:
    """Every row and seed (a job each, `jobs.run_jobs`), then the table's rows assembled; resumable
    (see the module docstring). `rows_named`: only these rows of the preset (a partial table, its
    caption and file names say so). `workers` > 1 runs that many jobs at once in worker processes
    (torch on the preset's `threads`, else one thread, each); `ray_address`: every job as a task on
    that Ray cluster instead (`ray_node_ip`: this machine's address there). The table is the same
    whichever runs the jobs.

    :param spec: the table spec (`table_spec.load_spec`)
    :param preset_name: one of the spec's presets
    :param runs_dir: where training and evaluation runs live (`RUNS/train`, `RUNS/eval`)
    :param progress: where the progress lines go
    :param workers: jobs at once on this machine
    :param device: where torch computes ("cpu" or "cuda")
    :param sources: where runs come from (`jobs.Sources`: train, `--trained` folders, `--archive`)
    :param rows_named: only these rows of the preset (a partial table)
    :param ray_address: run every job as a task on the Ray cluster there instead of here
    :param ray_node_ip: this machine's address on that cluster
    :return: the assembled rows (`table_statistics.TableResult`), for `table_files.write_table`
    """
    preset = spec.preset(preset_name)
    sources = sources or Sources()  # (by default: train, or find, or resume, in runs_dir)
    if workers < 1:
        raise TableError(f"workers must be at least 1, got {workers}")
    runs_dir = Path(runs_dir)
    start = time.perf_counter()
    rows = only_rows(spec, preset, rows_named)
    jobs = _preset_jobs(spec, preset, rows, runs_dir, device, sources, progress)
    if ray_address is None:
        outcomes = run_jobs(jobs, progress, workers)
    else:
        outcomes = run_jobs_on_ray(jobs, ray_address, progress, ray_node_ip)
    if sources.trained is not None:
        other_code_runs([outcome.train_run for outcome in outcomes if outcome.train_run], progress)
    results = _row_results(rows, jobs, outcomes)  # (training only: the trained rows)
    left_out = tuple(row.name for row in preset_rows(spec, preset) if row not in rows)
    return TableResult(spec, preset, results, time.perf_counter() - start, git_revision(), left_out)


def _preset_jobs(spec, preset, rows, runs_dir: Path, device: str, sources: Sources, progress) -> list[Job]:
    """The preset's jobs of these rows (each row's seeds; with `train_only`, those that train),
    announced with their cost where they train."""
    pairs = [(row, seed) for row, seed in table_jobs(spec, preset) if row in rows]
    if sources.train_only:  # only the jobs that train
        pairs = [(row, seed) for row, seed in pairs if trains(row)]
    if sources.trained is None:
        announce_training(preset, [p for p in pairs if trains(p[0])], runs_dir, device, progress)
    # torch's threads in every job, training (the option) and evaluation alike: the spec's, so that a
    # job's numbers do not depend on how many run at once (threads change the sums' order)
    return [
        Job(
            spec=spec,
            preset=preset,
            row=row,
            seed=seed,
            runs_dir=runs_dir,
            device=device,
            sources=sources,
            threads=preset.threads,
        )  # fmt: skip
        for row, seed in pairs
    ]


def _row_results(rows, jobs: list[Job], outcomes) -> list[RowResult]:
    """The jobs' outcomes gathered per row, in the rows' order: each seed's episodes and runs."""
    per_row: dict[str, RowResult] = {}
    for job, outcome in zip(jobs, outcomes, strict=True):
        result = per_row.setdefault(job.row.name, RowResult(job.row, [], [], [], 0.0))
        result.episodes.append(outcome.cells)
        result.train_runs.append(outcome.train_run)
        result.eval_runs.append(outcome.eval_run)
        result.seconds += outcome.seconds
    return [per_row[row.name] for row in rows if row.name in per_row]
