"""The run-directory store that training (runs.py), evaluation (evaluate.py) and shipping (zoo.py)
share. A run directory is named by a digest of its identity, the record of everything that decides its
numbers (`digest`). Its config.json is written once, holding the identity and what is only recorded
beside it (the git revision, the plugin's file); opened again, the directory must hold the same
identity, else it is refused, never mixed or overwritten (`open_directory`). Its result files and
checkpoints carry their sha256 beside them (kgnavbench/files.py: `write_with_checksum`,
`checksum_matches`), so that a file changed after it was written is refused, and a run resumes from
what is there and checks out. A helper without a stage number.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from .errors import KgnavbenchError
from .files import atomic_write, first_line, git_revision, machine, symbolic_link


def digest(identity: dict, digits: int) -> str:
    """The first `digits` hex digits of the sha256 of the identity's canonical JSON (sorted keys): a
    run directory's name. Values JSON cannot hold are written as their str()."""
    text = json.dumps(identity, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:digits]


def read_record(path: Path, keys: tuple[str, ...], error: type[KgnavbenchError]) -> dict:
    """A run's JSON file (config.json, finished.json) as an object holding `keys`, or `error` naming
    the file and what is wrong."""
    if symbolic_link(path):
        raise error(symbolic_link(path))
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        raise error(f"{path.parent} has no {path.name}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise error(f"{path} is unreadable ({type(e).__name__}: {first_line(e)})") from e
    missing = [key for key in keys if not isinstance(record, dict) or key not in record]
    if missing:
        raise error(f"{path} is not a run's {path.name}: no {', '.join(missing)}")
    return record


def open_directory(
    directory: Path,
    identity: dict,
    error: type[KgnavbenchError],
    what: str,
    under: str | None = None,
    recorded: dict | None = None,
) -> None:
    """Create `directory` with its config.json, or check that an existing one is this run's. The
    file holds the identity (at its top level, or under the key `under`) and `recorded` (fields kept
    beside it that decide nothing: the git revision and the machine are always among them). Another
    identity there, or an unreadable file, is `error` naming the fields that differ: `what` says what
    the directory holds ("a run", "an evaluation")."""
    path = directory / "config.json"
    recorded = {**(recorded or {}), "git_revision": git_revision(), "machine": machine()}
    if not path.exists():
        saved = {under: identity, **recorded} if under else {**identity, **recorded}
        try:
            atomic_write(path, json.dumps(saved, indent=2) + "\n")
        except OSError as e:
            raise error(f"cannot write {path}: {e.strerror or e}; choose another --runs folder") from e
        return
    try:
        old = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise error(f"{path} is unreadable ({first_line(e)}); delete {directory} to start over") from e
    old = old if isinstance(old, dict) else {}  # any JSON at all: compared field by field
    if under:
        known = old.get(under) if isinstance(old.get(under), dict) else {}
    else:
        known = {k: v for k, v in old.items() if k not in recorded}
    if known != identity:
        differ = sorted(k for k in set(identity) | set(known) if known.get(k) != identity.get(k))
        raise error(
            f"{directory} holds {what} with another config (differs in {', '.join(differ) or 'config'}); "
            "refusing to mix them: delete it or use another --runs folder"
        )
