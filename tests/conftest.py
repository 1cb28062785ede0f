"""Shared fixtures, built once per session: a hermetic state-graph cache, FloorPlan1's tasks and the smoke
table. `make test` runs the suite on one pytest-xdist worker per core; what is built once is built once
for all of them (`_made_once`)."""

import fcntl
import json
import os
import secrets
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from kgnavbench import tasks

# Ray's token authentication for every cluster the suite starts (tests/test_ray.py) and every driver
# in it, set before anything imports Ray (which reads it once per process): a token made for this run
# of the suite, which nothing else on the machine knows. Nobody on the network can run code on the
# suite's clusters while it runs.
os.environ["RAY_AUTH_MODE"] = "token"
os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)


# the kitchens the whole suite builds into its cache (FloorPlan1 the most, the val split's for the
# evaluations of a whole split, FloorPlan13 for the smoke table, FloorPlan25 for the damaged-cache tests)
SUITE_KITCHENS = ",".join(f"FloorPlan{n}" for n in (1, 2, 5, 13, 21, 23, 25, 26, 28))


# The files that take longest, longest first (seconds on 2 xdist workers, 2026-12-07: ray 179, table 126,
# train 124, distributed 54, errors 47, evaluate_policy 42, stacking 37; the rest 25 or less). `make
# test` hands out whole files in collection order (`--no-loadscope-reorder`), each to the first worker
# with room: so that no long file starts last and runs alone.
LONGEST_FIRST = ("test_ray", "test_table", "test_train", "test_distributed", "test_errors")
LONGEST_FIRST += ("test_evaluate_policy", "test_stacking")


def pytest_collection_modifyitems(items):
    """Collection order: LONGEST_FIRST's files, then the others by name; each file's tests in its own
    order (a stable sort)."""
    rank = {name: n for n, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.stem, len(rank)))


XDIST = os.environ.get("PYTEST_XDIST_WORKER") is not None  # a worker of `pytest -n N`


def _made_once(tmp_path_factory, name: str, make) -> Path:
    """A folder that `make(folder)` fills once per run of the suite: under pytest-xdist, once for all
    its workers (the first to ask makes it under a lock; the others wait for it and read it, and
    must not write in it), so that two cores do not build the same thing twice. Where `make` raised,
    the other workers fail with its error rather than try again."""
    if not XDIST:
        folder = tmp_path_factory.mktemp(name)
        make(folder)
        return folder
    shared = tmp_path_factory.getbasetemp().parent  # the run's folder, above each worker's own
    folder, made, failed = shared / name, shared / f"{name}.made", shared / f"{name}.failed"
    with open(shared / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if failed.exists():
            pytest.fail(f"another worker's {name} failed: {failed.read_text()}")
        if not made.exists():
            folder.mkdir()
            try:
                make(folder)
            except BaseException as e:
                failed.write_text(f"{type(e).__name__}: {e}")
                raise
            made.touch()
    return folder


@pytest.fixture(scope="session", autouse=True)
def hermetic_cache(tmp_path_factory, request):
    """Point the state-graph cache at a fresh folder, so no test reads or writes the user's cache. A run
    of the whole suite builds its kitchens first with `kgnavbench prepare`, one process per core (one
    process built them in 84 s, measured; the tests that need them would build them one at a time),
    once for all workers; each worker takes its own copy, since some tests damage cache files."""
    root = tmp_path_factory.mktemp("kgnavbench-cache")
    old = os.environ.get("KGNAVBENCH_CACHE")

    def prepare(folder) -> None:
        argv = [sys.executable, "-m", "kgnavbench", "prepare", "--kitchens", SUITE_KITCHENS]
        env = {**os.environ, "KGNAVBENCH_CACHE": str(folder)}
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, env=env)

    if len(request.session.items) > 100 and not XDIST:
        prepare(root)
    elif len(request.session.items) > 100:
        shutil.copytree(
            _made_once(tmp_path_factory, "kgnavbench-prepared", prepare), root, dirs_exist_ok=True
        )
    os.environ["KGNAVBENCH_CACHE"] = str(root)
    try:
        yield root
    finally:
        if old is None:
            os.environ.pop("KGNAVBENCH_CACHE", None)
        else:
            os.environ["KGNAVBENCH_CACHE"] = old


@pytest.fixture(scope="session")
def floorplan1_tasks(hermetic_cache):
    """FloorPlan1's state graph (built into the hermetic cache, ~8 s), targets and fixed episodes."""
    return tasks.load_tasks("FloorPlan1")


@pytest.fixture
def local(tmp_path, monkeypatch):
    """A researcher's ./baselines folder in a fresh working directory: its plugins join the shipped ones."""
    folder = tmp_path / "baselines"
    folder.mkdir()
    monkeypatch.chdir(tmp_path)
    return folder


@pytest.fixture(scope="session")
def smoke_table(tmp_path_factory, hermetic_cache):
    """`kgnavbench table --preset smoke` as `make test` would run it, two jobs at a time in worker
    processes, run once: (its runs and output folder, the finished process). tests/test_table.py checks
    it end to end; tests/test_ray.py compares Ray's table with it. Read it only: another worker may be
    reading it too (copy it to run a command in it)."""
    argv = [sys.executable, "-m", "kgnavbench", "table", "--preset", "smoke", "--workers", "2"]

    def run(folder) -> None:
        env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache)}
        done = subprocess.run(
            [*argv, "--runs", str(folder), "--out", str(folder)], capture_output=True, text=True, env=env
        )
        process = {"returncode": done.returncode, "stdout": done.stdout, "stderr": done.stderr}
        (folder / "process.json").write_text(json.dumps(process))

    folder = _made_once(tmp_path_factory, "smoke-table", run)
    process = json.loads((folder / "process.json").read_text())
    return folder, subprocess.CompletedProcess(argv, **process)
