"""Claims: one process at a time on one thing (a training run's directory), among the processes of one
machine or of several machines that share the runs folder.

A claim is a small JSON file (host, pid, start time) created with O_CREAT | O_EXCL, which the file system
grants to one process only. It is released (deleted) when the work ends. A claim whose process is gone, on
this same host, is stale (a killed run): the next claimant moves it aside (a rename, which one process
alone wins) and claims afresh. A claim from another host is never judged stale from here (its pid means
nothing on this machine): the message names the host, and deleting the claim file frees it. Except on a
Ray cluster (`ray_jobs.run_jobs_on_ray`): there a claim also records its Ray node and its cluster's head,
and a claim whose node Ray reports dead, or whose cluster is gone (its head answers no more: a rerun
on a fresh cluster after the head was lost), is stale wherever it is read, so that a job retried on
another node, or on another cluster, takes over its run directory.
"""

from __future__ import annotations

import json
import os
import socket
import time
from contextlib import contextmanager
from pathlib import Path

from .errors import KgnavbenchError
from .files import one_line


class ClaimError(KgnavbenchError, RuntimeError):
    """The thing is claimed by another live process (the message says which)."""


# on a Ray cluster: this process's node and cluster (its head's GCS address), the nodes Ray reported
# dead when its task started, and every node it knew of then
_cluster: dict = {"node": None, "dead": frozenset(), "nodes": frozenset(), "head": None}


def on_cluster(node: str | None, dead_nodes=(), nodes=(), head: str | None = None) -> None:
    """Claims made from now on record Ray node `node` and its cluster's head `head`; a claim recorded
    by one of `dead_nodes` is stale (its process died with its node, on whatever host), and so is one
    recorded on another cluster whose head no longer answers (that cluster is gone, its processes with
    it), or on this cluster by a node it does not know (`nodes`). None: not on a cluster."""
    _cluster.update(node=node, dead=frozenset(dead_nodes), nodes=frozenset(nodes), head=head)


def _me() -> dict:
    me = {"host": socket.gethostname(), "pid": os.getpid(), "since": round(time.time(), 3)}
    if _cluster["node"] is None:
        return me
    return {**me, "node": _cluster["node"], "head": _cluster["head"]}


def answers(head: str, seconds: float = 3.0) -> bool:
    """Whether something listens at HOST:PORT (a Ray cluster's head)."""
    host, _, port = head.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=seconds):
            return True
    except (OSError, ValueError):
        return False


def _of_a_lost_cluster(record: dict) -> str | None:
    """Why a claim made on a Ray cluster holds nothing any more, read from a task on a cluster: its
    node is dead, or unknown to this cluster, or its cluster's head is gone; None where none of these."""
    node, head = record.get("node"), record.get("head")
    if node in _cluster["dead"]:
        return f"its Ray node {node} is dead"
    if _cluster["node"] is None or not isinstance(head, str):
        return None
    if head == _cluster["head"]:
        return f"its Ray node {node} is not in this cluster" if node not in _cluster["nodes"] else None
    return None if answers(head) else f"its Ray cluster (head {head}) is gone"


def read(path: Path) -> dict | None:
    """The claim's record; None where there is none, or where it is unreadable (being written)."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


WRITING_GRACE = 10.0  # seconds a claim file may stay unreadable while its creator writes it


def stale(record: dict | None, path: Path | None = None) -> bool:
    """A claim that holds nothing any more: of this host with its process gone, or of a dead Ray node, or
    malformed (no host name, or on this host no whole-number pid), or, given its `path`, unreadable
    for longer than a creator takes to write it (an empty file left by a crash). An unreadable claim
    younger than that is being written: not stale."""
    if record is None:
        if path is None:
            return False
        try:
            return time.time() - os.stat(path).st_mtime > WRITING_GRACE
        except OSError:
            return False
    if record.get("node") is not None:
        lost = _of_a_lost_cluster(record)
        if lost:  # its process went with its node or cluster, on whatever host: say so in the run's log
            print(f"kgnavbench: taking over {path or 'a claim'} of {describe(record)}: {lost}", flush=True)
            return True
    host, pid = record.get("host"), record.get("pid")
    if not isinstance(host, str):
        return True
    if host != socket.gethostname():
        return False  # another machine's pid means nothing here
    return not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0 or not _alive(pid)


def claim(path: Path | str) -> bool:
    """Claim `path` for this process: True if it is now ours; False if a live process (or a finished
    piece of work) holds it. A stale claim is taken over."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if not stale(read(path), path):
                return False
            aside = path.with_name(f"{path.name}.stale-{os.getpid()}")
            try:  # only one of the processes that found it stale moves it aside
                os.rename(path, aside)
            except FileNotFoundError:
                return False
            aside.unlink(missing_ok=True)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(_me()) + "\n")
        return True
    return False


def release(path: Path | str) -> None:
    """Give up our claim (if it is still ours)."""
    path = Path(path)
    record = read(path)
    if record and record.get("pid") == os.getpid() and record.get("host") == socket.gethostname():
        path.unlink(missing_ok=True)


def describe(record: dict | None) -> str:
    """Who holds a claim, from its record, whatever the record's fields hold."""
    if record is None:
        return "another process (its claim is being written)"
    since = record.get("since")
    try:
        if not isinstance(since, (int, float)) or isinstance(since, bool):
            raise TypeError(since)
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(since))
    except (TypeError, ValueError, OverflowError, OSError):
        when = f"an unknown time ({_short(since, 40)})"
    return f"pid {_short(record.get('pid'))} on {_short(record.get('host'))} since {when}"


def _short(value, width: int = 60) -> str:
    """A record's field for a message: one short line whatever it holds."""
    return one_line(value if isinstance(value, str) else repr(value))[:width]


@contextmanager
def held(path: Path | str, what: str):
    """Hold the claim on `path` while the block runs; ClaimError naming the holder if another live
    process holds it."""
    path = Path(path)
    if not claim(path):
        raise ClaimError(
            f"{what} is in use by {describe(read(path))}; wait for it to end (or, if that process is "
            f"gone on another machine, delete {path})"
        )
    try:
        yield
    finally:
        release(path)
