"""A real install: build the wheel, install it (not editable) into a throw-away venv that borrows the
already-installed torch and friends, and run `kgnavbench` from another directory."""

from __future__ import annotations

import os
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def sh(*argv, cwd, env=None, timeout=300) -> subprocess.CompletedProcess:
    result = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert result.returncode == 0, f"{argv}\n{result.stdout}\n{result.stderr}"
    return result


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    # --no-build-isolation: build with this environment's setuptools, no download
    sh(
        sys.executable,
        "-m",
        "pip",
        "wheel",
        "--no-deps",
        "--no-build-isolation",
        "-q",
        "-w",
        str(out),
        ".",
        cwd=ROOT,
    )
    (path,) = out.glob("kgnavbench-*.whl")
    return path


def test_the_wheel_ships_the_data_and_the_baselines_and_declares_its_imports(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert "kgnavbench/data/tasks.json.gz" in names
    assert "kgnavbench/data/kitchens/FloorPlan30.json.gz" in names
    assert "kgnavbench/data/object_types.json" in names
    assert {"kgnavbench_baselines/random_walk.py", "kgnavbench_baselines/oracle.py"} <= set(names)
    (metadata,) = [n for n in names if n.endswith(".dist-info/METADATA")]
    requires = [
        line.split(":", 1)[1].strip()
        for line in zipfile.ZipFile(wheel).read(metadata).decode().splitlines()
        if line.startswith("Requires-Dist:")
    ]
    for package in ("numpy", "gymnasium", "torch==2.13.0", "pettingzoo", "pymunk", "rerun-sdk"):
        assert any(r.replace(" ", "").startswith(package) for r in requires), (package, requires)


def test_an_installed_kgnavbench_evaluates_from_another_directory(
    wheel, tmp_path, hermetic_cache, floorplan1_tasks
):
    venv = tmp_path / "venv"
    sh(sys.executable, "-m", "venv", "--without-pip", str(venv), cwd=tmp_path)
    python = venv / "bin" / "python"
    site = Path(
        subprocess.run(
            [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    )
    # borrow torch, numpy, OpenCV, ... from this environment (no second torch download); the .pth puts
    # them after the venv's own site-packages, so the installed kgnavbench wins over the editable one
    (site / "borrowed.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    sh(
        sys.executable,
        "-m",
        "pip",
        "--python",
        str(python),
        "install",
        "-q",
        "--no-deps",
        str(wheel),
        cwd=tmp_path,
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "KGNAVBENCH_CACHE": str(hermetic_cache), "PYTHONPATH": ""}
    kgnavbench = str(venv / "bin" / "kgnavbench")

    where = sh(str(python), "-c", "import kgnavbench; print(kgnavbench.__file__)", cwd=elsewhere, env=env)
    assert where.stdout.strip().startswith(str(venv))  # the installed copy, not the source tree

    methods = sh(kgnavbench, "methods", cwd=elsewhere, env=env).stdout
    assert "random_walk" in methods and "oracle" in methods
    assert str(venv) in methods  # the shipped baselines come from the installed package

    argv = [kgnavbench, "eval", "--method", "random_walk", "--episodes", "1", "--kitchens", "FloorPlan1"]
    result = sh(*argv, cwd=elsewhere, env=env)
    assert "seen kitchens / seen targets" in result.stdout
    assert (elsewhere / "runs" / "eval").is_dir()

    # a researcher's own plugin in ./baselines joins the shipped ones
    (elsewhere / "baselines").mkdir()
    (elsewhere / "baselines" / "mine.py").write_text(
        'DESCRIPTION = "my method"\n'
        "class P:\n    def reset(self, agent): pass\n"
        "    def act(self, obs, infos): return {a: 9 for a in obs}\n"
        "def make_policy(config, spec):\n    return P()\n"
    )
    methods = sh(kgnavbench, "methods", cwd=elsewhere, env=env).stdout
    assert "mine" in methods and "random_walk" in methods


def test_a_stage_imports_only_the_stages_before_it():
    """The data flow of DESIGN.md: every `Stage N` module imports stages numbered below N only (the
    helpers without a stage number, files, claims and intervals, are free to use)."""
    import re

    package = ROOT / "kgnavbench"
    number = {}
    for path in package.glob("*.py"):
        found = re.match(r'"""Stage (\d+) ', path.read_text())
        if found:
            number[path.stem] = int(found.group(1))
    assert len(number) >= 15 and len(set(number.values())) == len(number), number
    for stage, n in number.items():
        text = (package / f"{stage}.py").read_text()
        imported = re.findall(r"^\s*from \.(\w+) import", text, re.M)
        for names in re.findall(r"^\s*from \. import ([\w, ]+)", text, re.M):
            imported += [x.strip() for x in names.split(",")]
        later = [m for m in imported if number.get(m, -1) >= n]
        assert not later, f"{stage} (stage {n}) imports {later}"
