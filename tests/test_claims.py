"""Claims (kgnavbench/claims.py): one process at a time on a run or a table job; stale claims of dead
processes on this host are taken over, done claims and other hosts' claims are not."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import time

import pytest

from kgnavbench import claims


def _record(pid: int, host: str | None = None, **extra) -> str:
    return json.dumps({"host": host or socket.gethostname(), "pid": pid, "since": time.time(), **extra})


def test_a_claim_is_granted_once_and_released(tmp_path):
    path = tmp_path / "deep" / "job.claim"
    assert claims.claim(path)
    assert claims.read(path)["pid"] == os.getpid()
    assert not claims.claim(path)  # held, by a live process (this one)
    claims.release(path)
    assert not path.exists() and claims.claim(path)


def test_a_dead_processs_claim_is_taken_over_and_a_live_ones_is_not(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    path = tmp_path / "job.claim"
    path.write_text(_record(dead.pid))
    assert claims.stale(claims.read(path))
    assert claims.claim(path) and claims.read(path)["pid"] == os.getpid()
    assert [p.name for p in tmp_path.iterdir()] == ["job.claim"]  # the stale one moved aside and gone

    live = subprocess.Popen(["sleep", "30"])
    try:
        path.write_text(_record(live.pid))
        assert not claims.stale(claims.read(path)) and not claims.claim(path)
        message = f"in use by pid {live.pid} on {socket.gethostname()}"
        with pytest.raises(claims.ClaimError, match=message), claims.held(path, "run X"):
            pass
    finally:
        live.kill()
        live.wait()


def test_claims_of_other_hosts_and_half_written_claims_are_never_stale(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    path = tmp_path / "trainer.claim"
    path.write_text(_record(dead.pid, host="another-machine"))
    assert not claims.claim(path)  # its pid means nothing here
    with pytest.raises(claims.ClaimError, match="another-machine.*delete"), claims.held(path, "run X"):
        pass
    path.write_text("")  # created, not yet written
    assert not claims.claim(path)


def test_held_releases_and_a_claim_of_a_dead_ray_node_is_taken_over_from_any_host(tmp_path):
    path = tmp_path / "trainer.claim"
    with claims.held(path, "run X"):
        assert claims.read(path)["pid"] == os.getpid() and "node" not in claims.read(path)
    assert not path.exists()
    # a claim made on another host by a task of a Ray node: live until Ray reports that node dead
    other = {"host": "elsewhere", "pid": 1, "since": 0.0, "node": "ab12"}
    path.write_text(json.dumps(other))
    try:
        claims.on_cluster("cd34", dead_nodes=())
        assert not claims.claim(path)
        claims.on_cluster("cd34", dead_nodes=("ab12",))
        assert claims.claim(path) and claims.read(path)["node"] == "cd34"
    finally:
        claims.on_cluster(None)
    claims.release(path)
    assert not path.exists()


def test_malformed_and_abandoned_claims_are_taken_over_or_named_without_a_traceback(tmp_path):
    """A claim file left empty by a crash (older than a creator takes to write one), or with fields of
    the wrong kind, does not block forever; an odd start time is named, not a traceback."""
    path = tmp_path / "trainer.claim"
    path.write_text("")
    old = time.time() - 2 * claims.WRITING_GRACE
    os.utime(path, (old, old))
    assert claims.claim(path)  # empty and old: abandoned
    claims.release(path)
    for record in ({"host": 5, "pid": 1}, {"host": socket.gethostname(), "pid": "x"}, {"pid": 1}):
        path.write_text(json.dumps(record))
        assert claims.claim(path), record
        claims.release(path)
    for since in ("yesterday", 1e300, None, float("nan")):
        path.write_text(json.dumps({"host": "another-machine", "pid": 7, "since": since}))
        match = "another-machine since an unknown time"
        with pytest.raises(claims.ClaimError, match=match), claims.held(path, "run X"):
            pass


def test_a_claim_of_a_lost_cluster_is_taken_over_on_a_new_one_and_a_live_ones_is_not(tmp_path, capsys):
    """After a head is lost, a rerun on a fresh cluster finds claims that tasks of the old cluster left,
    on other hosts: the old head answers no more, so they are taken over (and the takeover is said); a
    claim of a cluster whose head still answers, or of a live node of this cluster, still refuses."""
    import socket

    path = tmp_path / "trainer.claim"
    with socket.socket() as live_head, socket.socket() as gone:
        live_head.bind(("127.0.0.2", 0))
        live_head.listen()
        gone.bind(("127.0.0.2", 0))  # bound, never listening: nothing answers there
        live = f"127.0.0.2:{live_head.getsockname()[1]}"
        lost = f"127.0.0.2:{gone.getsockname()[1]}"
        try:
            claims.on_cluster("new1", dead_nodes=(), nodes=("new1", "new2"), head="127.0.0.2:1")
            # another live cluster's claim (its head answers), on another host: refused
            path.write_text(
                json.dumps({"host": "node-b", "pid": 7, "since": 0.0, "node": "old", "head": live})
            )
            assert not claims.claim(path)
            # a live node of this cluster: refused
            path.write_text(
                json.dumps({"host": "node-b", "pid": 7, "since": 0.0, "node": "new2", "head": "127.0.0.2:1"})
            )
            assert not claims.claim(path)
            # a node this cluster does not know, recorded under this cluster's head: taken over
            path.write_text(
                json.dumps({"host": "node-b", "pid": 7, "since": 0.0, "node": "x", "head": "127.0.0.2:1"})
            )
            assert claims.claim(path)
            path.unlink()
            # the lost cluster's claim: taken over, with the evidence in the log
            path.write_text(
                json.dumps({"host": "node-b", "pid": 7, "since": 0.0, "node": "old", "head": lost})
            )
            assert claims.claim(path)
            record = claims.read(path)
            assert record["node"] == "new1" and record["head"] == "127.0.0.2:1"
            assert f"its Ray cluster (head {lost}) is gone" in capsys.readouterr().out
        finally:
            claims.on_cluster(None)
    claims.release(path)
    assert not path.exists()
