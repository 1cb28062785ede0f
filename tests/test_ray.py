"""`kgnavbench table --ray`: a table's jobs as Ray tasks on a local cluster of two one-CPU nodes.

The cluster stays on loopback addresses other than 127.0.0.1 (Ray swaps 127.0.0.1 and localhost for
the machine's interface address): a head on 127.0.0.2 and a node on 127.0.0.3. Each node is started
under its own session (`ray start --block` in a new session), and stopped by the pids of that session:
Ray's agents rename themselves and are re-parented to init, so neither a command-line pattern nor
`ray stop` (which stops every Ray of the machine) finds exactly what this test started.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from kgnavbench.cli import main
from kgnavbench.table_spec import SPEC_FILE

ray = pytest.importorskip("ray", reason="the Ray tests need kgnavbench[ray] (in .[dev])")

HEAD, NODE = "127.0.0.2", "127.0.0.3"
RAY = str(Path(sys.executable).with_name("ray"))


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def _session_pids(sid: int) -> list[int]:
    """Every live process of session `sid` (field 6 of /proc/PID/stat)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # fields[0] is the state; [3] the session
            pids.append(int(stat.parent.name))
    return pids


def _kill_session(sid: int) -> None:
    for _ in range(50):
        pids = _session_pids(sid)
        if not pids:
            return
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        time.sleep(0.1)


class Cluster:
    """Two one-CPU nodes, each its own session: `address` for ray.init, `kill_node()` kills the second
    node's session with SIGKILL (its raylet, agents and workers at once, as a machine that dies)."""

    def __init__(self, env: dict, temp_dir: str):
        self.port = _free_port(HEAD)
        self.address = f"{HEAD}:{self.port}"
        self.temp_dir = temp_dir
        common = ["--num-cpus=1", "--block", "--disable-usage-stats", f"--temp-dir={temp_dir}"]
        self.head = subprocess.Popen(
            [RAY, "start", "--head", f"--node-ip-address={HEAD}", f"--port={self.port}",
             "--include-dashboard=false", f"--dashboard-host={HEAD}",
             f"--dashboard-port={_free_port(HEAD)}", *common],
            env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        self.nodes = [self.head]
        self._wait_for(1)
        self.node = self.start_node(env)

    def start_node(self, env: dict) -> subprocess.Popen:
        node = subprocess.Popen(
            [RAY, "start", f"--address={self.address}", f"--node-ip-address={NODE}", "--num-cpus=1",
             "--block", "--disable-usage-stats"],
            env=env, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        self.nodes.append(node)
        self._wait_for(2)
        return node

    def _wait_for(self, alive: int, timeout: float = 90.0) -> None:
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                ray.init(address=self.address, _node_ip_address=HEAD, logging_level="ERROR")
                n = sum(node["Alive"] and node["Resources"].get("CPU", 0) > 0 for node in ray.nodes())
            except (ConnectionError, RuntimeError):
                n = 0
            finally:
                ray.shutdown()
            if n >= alive:
                return
            time.sleep(1.0)
        self.stop()
        pytest.fail(f"the local Ray cluster did not reach {alive} live nodes in {timeout:.0f} s")

    def kill_node(self) -> None:
        _kill_session(self.node.pid)
        self.node.wait(timeout=30)

    def stop(self) -> None:
        for node in reversed(self.nodes):
            _kill_session(node.pid)
            with contextlib.suppress(subprocess.TimeoutExpired):
                node.wait(timeout=30)
        shutil.rmtree(self.temp_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster(hermetic_cache):
    """One cluster for every test here (Ray takes seconds to start); the nodes see the driver's
    state-graph cache and numerics through the table's runtime environment. Private: on loopback
    addresses, with Ray's token authentication and the suite's own token (tests/conftest.py)."""
    assert os.environ.get("RAY_AUTH_MODE") == "token" and len(os.environ.get("RAY_AUTH_TOKEN", "")) == 64
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    temp_dir = tempfile.mkdtemp(prefix="kgr", dir="/tmp")  # short: Ray's socket paths must fit 107 bytes
    cluster = Cluster(env, temp_dir)
    try:
        yield cluster
    finally:
        cluster.stop()


def _spec(tmp: Path, preset_block: str) -> Path:
    """The committed spec with one more preset."""
    path = tmp / "spec.toml"
    text = SPEC_FILE.read_text()
    head, tail = text.split("[presets.smoke]\n", 1)
    path.write_text(f"{head}{preset_block}\n\n[presets.smoke]\n{tail}")
    return path


def _tables(out: Path, preset: str) -> dict[str, str]:
    """The written table's files, with the wall time (the one thing that differs) blanked."""
    return {
        p.name: re.sub(r"wall time [0-9.]+ min", "wall time T", p.read_text())
        for p in sorted(out.glob(f"table1-{preset}*"))
    }


def test_the_smoke_table_under_ray_is_the_single_process_table(cluster, smoke_table, tmp_path, capsys):
    one, plain = smoke_table  # the same table run by worker processes on this machine
    assert plain.returncode == 0, plain.stderr[-2000:]
    argv = ["table", "--preset", "smoke", "--runs", str(tmp_path / "ray"), "--out", str(tmp_path / "ray")]
    assert main([*argv, "--ray", cluster.address, "--ray-node-ip", HEAD]) == 0
    printed = capsys.readouterr().out
    assert re.search(r"== ray: 0 running, \d+ done, 0 retried, 0 failed, 0 waiting", printed), printed[-2000:]
    plain, on_ray = _tables(one, "smoke"), _tables(tmp_path / "ray", "smoke")
    assert len(plain) == 4 and plain == on_ray
    assert not (tmp_path / "ray" / "ray").exists() or not any((tmp_path / "ray" / "ray").iterdir())


def _retried_preset() -> str:
    """The smoke preset as one learned row, two seeds, trained 12 times longer: long enough to kill."""
    smoke = SPEC_FILE.read_text().split("[presets.smoke]\n", 1)[1].split("\n\n", 1)[0]
    smoke = re.sub(r"(?m)^frames = .*$", "frames = 12000", smoke)
    smoke = re.sub(r"(?m)^seeds = .*$", "seeds = 2", smoke)
    smoke = re.sub(r"(?m)^eval_kitchens = .*$", 'eval_kitchens = ["FloorPlan1"]', smoke)
    smoke = smoke.replace('val_every = "500"', 'val_every = "4000"')
    assert 'val_every = "4000"' in smoke and "frames = 12000" in smoke
    return f'[presets.retried]\nrows = ["LSTM A3C"]\n{smoke}'


def test_a_node_killed_during_training_its_job_is_retried_and_resumes(cluster, tmp_path, capsys):
    """Two training jobs, one per node; the second node dies with SIGKILL while its job trains (after
    its first last.pt): Ray retries the job on the head, the trainer resumes from last.pt (taking over
    the dead process's claim on the run), and the table is the single process's."""
    spec = _spec(tmp_path, _retried_preset())
    common = ["table", "--spec", str(spec), "--preset", "retried"]
    runs = tmp_path / "ray"
    killed = {}

    def kill_when_the_nodes_job_has_a_checkpoint() -> None:
        deadline = time.time() + 240
        while time.time() < deadline and not killed:
            for attempts in (runs / "ray").glob("*/job-*"):
                record = json.loads(attempts.read_text().splitlines()[0])
                if record["pid"] not in _session_pids(cluster.node.pid):
                    continue  # the head's job
                run_dirs = [p.parent for p in (runs / "train").glob("*/trainer.claim")]
                for run_dir in run_dirs:
                    claim = json.loads((run_dir / "trainer.claim").read_text())
                    if claim["pid"] == record["pid"] and (run_dir / "last.pt").exists():
                        killed["run"] = run_dir
                        cluster.kill_node()
                        return
            time.sleep(0.2)

    killer = threading.Thread(target=kill_when_the_nodes_job_has_a_checkpoint, daemon=True)
    killer.start()
    try:
        argv = [*common, "--runs", str(runs), "--out", str(runs), "--ray", cluster.address]
        assert main([*argv, "--ray-node-ip", HEAD]) == 0
    finally:
        killer.join(timeout=5)
        if killed:
            cluster.node = cluster.start_node({**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})
    printed = capsys.readouterr().out
    assert killed, "the second node never ran a training job with a checkpoint to kill"
    assert re.search(r"== ray: .*1 retried", printed), printed[-3000:]
    assert (
        main([*common, "--runs", str(tmp_path / "one"), "--out", str(tmp_path / "one"), "--workers", "1"])
        == 0
    )
    assert _tables(tmp_path / "one", "retried") == _tables(runs, "retried")
    # the retried run resumed: its metrics start once, then continue where last.pt left them
    frames = [
        int(line.split(",")[0]) for line in (killed["run"] / "metrics.csv").read_text().splitlines()[1:]
    ]
    assert frames == sorted(set(frames))


RAISES = '''"""A plugin whose policy raises: an application error, which Ray does not retry."""
DESCRIPTION = "raises"


def make_policy(config, spec):
    raise RuntimeError("this plugin always fails")
'''

FAILING = """[presets.failing]
frames = 1000
episodes = 1
seeds = 1
rows = ["Random walk", "Raises"]
train_kitchens = ["FloorPlan1"]
eval_kitchens = ["FloorPlan1"]

[[rows]]
name = "Raises"
method = "raises"
"""


def test_a_jobs_own_error_is_named_and_the_other_jobs_finish(cluster, local, tmp_path, capsys):
    """A row whose plugin raises (from ./baselines of the driver's working directory, where each task
    runs) fails once, not retried, named with its error; the other job finishes."""
    (local / "raises.py").write_text(RAISES)
    text = SPEC_FILE.read_text()
    preset, row = FAILING.split("[[rows]]")
    spec = tmp_path / "spec.toml"
    spec.write_text(text.replace("[presets.smoke]", preset + "[presets.smoke]", 1) + "\n[[rows]]" + row)
    argv = ["table", "--spec", str(spec), "--preset", "failing", "--runs", "runs", "--out", "out"]
    assert main([*argv, "--ray", cluster.address, "--ray-node-ip", HEAD]) == 2
    captured = capsys.readouterr()
    assert "== failed [2/2] Raises (seed 0)" in captured.out
    assert "1 of 2 jobs failed ([2/2] Raises (seed 0):" in captured.err
    assert "this plugin always fails" in captured.err
    assert len(list((tmp_path / "runs" / "eval").glob("random_walk-*/summary.json"))) == 1


def test_an_address_nothing_answers_at_is_one_line_at_once(tmp_path, capsys):
    """`--ray HOST:PORT` where no cluster listens: one line naming the address within seconds (ray.init
    would wait minutes), nothing trained, no attempts folder."""
    with socket.socket() as probe:  # a loopback port nothing listens on: bound here, never listened
        probe.bind(("127.0.0.2", 0))
        port = probe.getsockname()[1]
        t0 = time.monotonic()
        argv = ["table", "--preset", "smoke", "--runs", str(tmp_path / "runs"), "--ray", f"127.0.0.2:{port}"]
        assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--ray 127.0.0.2:{port}: nothing answers there" in err, err
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "runs" / "ray").exists() and not (tmp_path / "runs" / "train").exists()


def test_a_cluster_without_the_cpus_a_job_needs_is_refused_at_once(cluster, tmp_path, capsys):
    """Jobs that need more CPUs than the cluster has (here: 3 torch threads on two one-CPU nodes; a
    head started with --num-cpus=0 is the same case) are refused in one line naming the cluster,
    where Ray would wait forever; no attempts folder is left behind."""
    smoke = SPEC_FILE.read_text().split("[presets.smoke]\n", 1)[1].split("\n\n", 1)[0]
    wide = smoke.replace('threads = "1"', 'threads = "3"')
    assert wide != smoke
    spec = _spec(tmp_path, f"[presets.wide]\n{wide}")
    t0 = time.monotonic()
    argv = ["table", "--spec", str(spec), "--preset", "wide", "--runs", str(tmp_path / "runs")]
    assert main([*argv, "--ray", cluster.address, "--ray-node-ip", HEAD]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "has 2 CPUs and a job needs 3" in err and cluster.address in err, (
        err
    )
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "runs" / "ray").exists() and not (tmp_path / "runs" / "train").exists()


def test_a_cluster_whose_nodes_run_other_code_is_refused_at_once(cluster, tmp_path, capsys, monkeypatch):
    """Every node is asked for its Python, torch and kgnavbench revision before anything is scheduled
    (a task that takes no CPU, pinned to the node); one that differs from the driver's is named in one
    line and nothing runs. Faked on the driver's side: its revision here is one the nodes do not run."""
    from kgnavbench import ray_jobs

    monkeypatch.setattr(ray_jobs, "git_revision", lambda: "0" * 40)
    t0 = time.monotonic()
    argv = ["table", "--preset", "smoke", "--runs", str(tmp_path / "runs")]
    assert main([*argv, "--ray", cluster.address, "--ray-node-ip", HEAD]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--ray {cluster.address}: node " in err, err
    differs = err.split(" runs ", 1)[1].split("; every node")[0]
    assert differs.startswith("kgnavbench ") and differs.endswith("(here " + "0" * 40 + ")"), err
    assert time.monotonic() - t0 < 30
    assert not (tmp_path / "runs" / "ray").exists() and not (tmp_path / "runs" / "train").exists()


def test_the_environment_check_names_the_first_node_that_differs():
    from kgnavbench.ray_jobs import environment_problems

    here = {"Python": "3.11.2", "torch": "2.13.0", "kgnavbench": "abc"}
    assert environment_problems(here, {"a": dict(here), "b": dict(here)}) is None
    other = {**here, "torch": "2.12.1", "kgnavbench": "def"}
    assert environment_problems(here, {"b": other, "a": dict(here)}) == (
        "node b runs torch 2.12.1 (here 2.13.0), kgnavbench def (here abc)"
    )
    assert environment_problems(here, {"c": {"Python": "3.11.2"}}) == (
        "node c runs torch (none) (here 2.13.0), kgnavbench (none) (here abc)"
    )


def test_a_lost_head_ends_the_driver_with_one_line_and_the_command_that_resumes():
    """The driver's watch on the head: once its port has not answered for `lost_after` seconds, one
    line names the head and the command to run again (here given to a callback, not the process's end)."""
    from kgnavbench.ray_jobs import _watch_head

    with socket.socket() as server:
        server.bind((HEAD, 0))
        server.listen()
        head = f"{HEAD}:{server.getsockname()[1]}"
        said = []
        stop = _watch_head(
            head, "kgnavbench table --preset smoke --ray X", every=0.1, lost_after=0.5, lost=said.append
        )
        time.sleep(0.5)
        assert not said  # it answers
    t0 = time.monotonic()
    while not said and time.monotonic() - t0 < 10:
        time.sleep(0.05)
    stop.set()
    assert len(said) == 1 and said[0].startswith("kgnavbench: error: lost the Ray cluster's head at " + head)
    assert "`kgnavbench table --preset smoke --ray X` again to resume" in said[0]


def test_a_client_without_the_clusters_token_is_refused(cluster):
    """The test cluster runs code only for who holds its token: a driver without it (or with another)
    is refused (Ray's "InvalidAuthToken"), and never joins."""
    script = f"import ray; ray.init(address={cluster.address!r}, _node_ip_address={HEAD!r}); print('joined')"
    for token in ("", secrets.token_hex(32)):
        env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
        env |= {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token} if token else {}
        client = subprocess.Popen(
            [sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, start_new_session=True,
        )  # fmt: skip
        said, deadline = [], time.monotonic() + 60
        try:
            for (
                line
            ) in client.stdout:  # Ray retries a refused token once a second: its first refusal is enough
                said.append(line)
                if "InvalidAuthToken" in line or "joined" in line or time.monotonic() > deadline:
                    break
        finally:
            _kill_session(client.pid)
            client.wait(timeout=30)
        assert any("InvalidAuthToken" in line for line in said), "".join(said)[-2000:]
        assert not any(line.startswith("joined") for line in said)


# the last test of the module: it kills the module's cluster's head (the fixture's teardown stops the rest)
def test_a_head_killed_mid_table_ends_the_driver_with_one_line_that_resumes(cluster, tmp_path):
    """The head dies (SIGKILL of its whole session: GCS, raylet, workers) while a job trains: the driver
    ends within 90 s with exit 2 and one `kgnavbench: error:` line naming the lost head and the command
    that resumes, not Ray's page after its own minute; the run's checkpoint stays for the resume."""
    spec = _spec(tmp_path, _retried_preset())
    runs = tmp_path / "runs"
    argv = [sys.executable, "-m", "kgnavbench", "table", "--spec", str(spec), "--preset", "retried"]
    argv += ["--runs", str(runs), "--out", str(runs), "--ray", cluster.address, "--ray-node-ip", HEAD]
    driver = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while (
            not list(runs.glob("train/*/last.pt")) and driver.poll() is None and time.monotonic() < deadline
        ):
            time.sleep(0.1)
        assert driver.poll() is None and list(runs.glob("train/*/last.pt")), "no job trained to a checkpoint"
        _kill_session(cluster.head.pid)
        killed = time.monotonic()
        _, err = driver.communicate(timeout=120)
        took = time.monotonic() - killed
    finally:
        if driver.poll() is None:
            driver.kill()
    errors = [line for line in err.splitlines() if line.startswith("kgnavbench: error:")]
    assert driver.returncode == 2 and took < 90, (driver.returncode, took, err[-2000:])
    assert len(errors) == 1 and errors[0].startswith(
        f"kgnavbench: error: lost the Ray cluster's head at {HEAD}:"
    )
    assert "again to resume" in errors[0] and "--preset retried" in errors[0] and "Traceback" not in err
    assert list(runs.glob("train/*/last.pt"))  # what the resume starts from
