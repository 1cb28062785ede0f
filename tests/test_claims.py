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


def test_done_claims_other_hosts_and_half_written_claims_are_never_stale(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    path = tmp_path / "job.claim"
    path.write_text(_record(dead.pid, done=True))
    assert not claims.claim(path)  # finished work stays finished
    path.write_text(_record(dead.pid, host="another-machine"))
    assert not claims.claim(path)  # its pid means nothing here
    with pytest.raises(claims.ClaimError, match="another-machine.*delete"), claims.held(path, "run X"):
        pass
    path.write_text("")  # created, not yet written
    assert not claims.claim(path)


def test_done_marks_the_claim_and_held_releases_it(tmp_path):
    path = tmp_path / "job.claim"
    with claims.held(path, "run X"):
        assert claims.read(path)["pid"] == os.getpid()
    assert not path.exists()
    assert claims.claim(path)
    claims.done(path)
    assert claims.read(path)["done"] is True and not claims.claim(path)
