"""Stage 29 — ray_jobs: a table's jobs as Ray tasks on a cluster (`table --ray ADDRESS`).

`run_jobs_on_ray` submits every `jobs.Job` as a Ray task to a cluster whose nodes share the runs
folder, after checking what would keep them from running (no CPU in the cluster, a node whose Python,
torch or kgnavbench revision differs from the driver's). A task whose worker or node dies runs again
and resumes its run from last.pt (its claim is taken over, `claims.on_cluster`); a head that stops
answering ends the table with one line that says how to resume. The other engines are in jobs.py.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import platform
import shlex
import shutil
import socket
import sys
import threading
import time
from pathlib import Path

import torch

from . import claims
from .files import NUMERICS_ENV, first_line, git_revision
from .jobs import Job, JobOutcome, execute, time_left, trains
from .runs import imported_training_code_sha256
from .table_spec import TableError

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
    try:  # an unreadable file counts as no attempt yet, as a missing one does
        return len(path.read_text().splitlines())
    except OSError:
        return 0


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
        import ray.exceptions  # (`_await_outcomes` reads them: a broken install fails here, before any task)
    except ImportError as e:
        raise TableError("--ray needs Ray, an optional extra: pip install 'kgnavbench[ray]'") from e
    if not jobs:
        return []
    head, cpus = _join_cluster(ray, jobs, address, node_ip)
    watchdog = _watch_head(head, shlex.join(["kgnavbench", *sys.argv[1:]]))
    runs_dir = Path(jobs[0].runs_dir)
    attempts_dir = runs_dir / "ray" / f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    attempts_dir.mkdir(parents=True)
    board = _Board(jobs, attempts_dir)
    try:
        task = ray.remote(_ray_task)
        refs = {}
        for n, job in enumerate(jobs):
            job = dataclasses.replace(job, threads=job.threads or 1)
            options = dict(num_cpus=job.threads, max_retries=RAY_RETRIES, retry_exceptions=False)
            remote = task.options(name=board.title(n), **options)
            refs[remote.remote(job, board.title(n), str(board.attempts_file(n)), os.getcwd())] = n
        parallel = max(1, cpus // max(job.threads or 1 for job in jobs))
        joined = f"{address} (head {head})" if address != head else address  # "auto": the one it joined
        progress(f"== {len(jobs)} jobs on the Ray cluster at {joined} ({cpus} CPUs)")
        _await_outcomes(ray, refs, board, parallel, progress)
    finally:
        watchdog.set()
        ray.shutdown()
        shutil.rmtree(attempts_dir, ignore_errors=True)
        with contextlib.suppress(OSError):  # runs/ray, unless another driver keeps its attempts there
            attempts_dir.parent.rmdir()
    if board.failed:
        names = "; ".join(f"{board.title(n)}: {why}" for n, why in sorted(board.failed.items()))
        raise TableError(
            f"{len(board.failed)} of {len(jobs)} jobs failed ({names}); the others are done: fix the cause "
            "and run the same command again to resume"
        )
    return board.outcomes


def _join_cluster(ray, jobs: list[Job], address: str, node_ip: str | None) -> tuple[str, int]:
    """The driver joined to the cluster at `address`, checked before anything is scheduled (its port,
    its CPUs for the jobs' threads, its nodes' software): the head's address and the cluster's CPUs."""
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
    return head, cpus


class _Board:
    """What the driver knows of the jobs while they run: each one's outcome or failure, the times of
    those done (for the ETA), and the attempts file each task writes when it starts."""

    def __init__(self, jobs: list[Job], attempts_dir: Path):
        self.jobs, self.attempts_dir = jobs, attempts_dir
        self.kinds = [trains(job.row) for job in jobs]
        self.outcomes: list[JobOutcome | None] = [None] * len(jobs)
        self.failed: dict[int, str] = {}
        self.done: list[tuple[bool, float]] = []

    def title(self, n: int) -> str:
        return self.jobs[n].title(n + 1, len(self.jobs))

    def attempts_file(self, n: int) -> Path:
        return (self.attempts_dir / f"job-{n + 1:03d}").resolve()

    def status(self, parallel: int) -> str:
        counts = [_attempts(self.attempts_file(n)) for n in range(len(self.jobs))]  # each file read once
        started = [n for n, count in enumerate(counts) if count]
        retried = [n for n, count in enumerate(counts) if count > 1]
        ended = {n for n, o in enumerate(self.outcomes) if o is not None} | set(self.failed)
        running = [n for n in started if n not in ended]
        left = time_left(self.done, [k for n, k in enumerate(self.kinds) if n not in ended])
        eta = f", about {left / 60 / parallel:.0f} min left" if left is not None else ""
        return (
            f"== ray: {len(running)} running, {len(ended) - len(self.failed)} done, {len(retried)} retried, "
            f"{len(self.failed)} failed, {len(self.jobs) - len(ended) - len(running)} waiting{eta}"
        )


def _await_outcomes(ray, refs: dict, board: _Board, parallel: int, progress) -> None:
    """Each task's outcome onto the board as it ends (a job's own error, or a worker or node lost
    more times than it is retried, is a failure), with a status line at least every RAY_STATUS_EVERY s."""
    from ray.exceptions import RayError, RayTaskError

    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1, timeout=RAY_STATUS_EVERY)
        for ref in ready:
            n = refs[ref]
            try:
                board.outcomes[n] = ray.get(ref)
            except RayTaskError as e:  # the job's own error (its traceback went to the log above)
                cause = e.cause if e.cause is not None else e
                board.failed[n] = f"{type(cause).__name__}: {first_line(cause)}"
                progress(f"== failed {board.title(n)}: {board.failed[n]}")
                continue
            except RayError as e:  # its worker or node died, more times than it is retried
                board.failed[n] = f"lost after {RAY_RETRIES} retries ({type(e).__name__}: {first_line(e)})"
                progress(f"== failed {board.title(n)}: {board.failed[n]}")
                continue
            if not board.outcomes[n].reused:
                board.done.append((board.kinds[n], board.outcomes[n].seconds))
            progress(f"== done {board.title(n)} in {board.outcomes[n].seconds / 60:.1f} min")
        progress(board.status(parallel))
