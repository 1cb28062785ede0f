"""Shared fixtures, built once per session: a hermetic state-graph cache, FloorPlan1's tasks and the smoke
table."""

import os
import secrets
import subprocess
import sys

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


@pytest.fixture(scope="session", autouse=True)
def hermetic_cache(tmp_path_factory, request):
    """Point the state-graph cache at a fresh folder, so no test reads or writes the user's cache. A run
    of the whole suite builds its kitchens first with `kgnavbench prepare`, one process per core (one
    process built them in 84 s, measured; the tests that need them would build them one at a time)."""
    root = tmp_path_factory.mktemp("kgnavbench-cache")
    old = os.environ.get("KGNAVBENCH_CACHE")
    os.environ["KGNAVBENCH_CACHE"] = str(root)
    if len(request.session.items) > 100:
        argv = [sys.executable, "-m", "kgnavbench", "prepare", "--kitchens", SUITE_KITCHENS]
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
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
    it end to end; tests/test_ray.py compares Ray's table with it."""
    folder = tmp_path_factory.mktemp("smoke-table")
    argv = [sys.executable, "-m", "kgnavbench", "table", "--preset", "smoke", "--workers", "2"]
    argv += ["--runs", str(folder), "--out", str(folder)]
    env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache)}
    return folder, subprocess.run(argv, capture_output=True, text=True, env=env)
