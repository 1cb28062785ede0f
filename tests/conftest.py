"""Shared fixtures: a hermetic state-graph cache and FloorPlan1's tasks, built once per session."""

import os
import secrets

import pytest

from kgnavbench import tasks

# Ray's token authentication for every cluster the suite starts (tests/test_ray.py) and every driver
# in it, set before anything imports Ray (which reads it once per process): a token made for this run
# of the suite, which nothing else on the machine knows. Nobody on the network can run code on the
# suite's clusters while it runs.
os.environ["RAY_AUTH_MODE"] = "token"
os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)


@pytest.fixture(scope="session", autouse=True)
def hermetic_cache(tmp_path_factory):
    """Point the state-graph cache at a fresh folder, so no test reads or writes the user's cache."""
    root = tmp_path_factory.mktemp("kgnavbench-cache")
    old = os.environ.get("KGNAVBENCH_CACHE")
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
