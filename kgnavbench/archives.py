"""Stage 22 — archives: an evaluation's results files, and a finished evaluation kept in git. Each
kitchen's results are JSON lines whose fields have the types of `RESULT_TYPES`, written atomically
with their sha256 beside them (`write_results_file`). `pack_evaluation` writes a finished
evaluation's config.json and every episode as one CSV, with each kitchen file's sha256, into one xz'd
tar (the same bytes every time); `unpack_evaluation` rebuilds the evaluation's files byte for byte in
another runs folder, where the same config resumes from them (`table --archive`, `kgnavbench
episodes`).
"""

from __future__ import annotations

import hashlib
import io
import json
import sys
import time
from pathlib import Path

from .files import atomic_write, checksum_matches, first_line, write_with_checksum
from .kitchens import KITCHEN_NAMES
from .tasks import load_task_file
from .weights import EvalError

SPLITS = ("table", "train", "val", "test")


def kitchens_of_split(split: str) -> list[str]:
    """The kitchens an evaluation covers: 'table' = train + test (Table I), or one split."""
    splits = load_task_file()["splits"]
    if split == "table":
        names = splits["train"] + splits["test"]
    elif split in splits:
        names = splits[split]
    else:
        raise EvalError(f"unknown split {split!r}; choose one of {SPLITS}")
    return sorted(names, key=KITCHEN_NAMES.index)


# Result rows as JSON lines: the types every field must have (a file that breaks them is not summed).
RESULT_TYPES = {
    "kitchen": str,
    "target": str,
    "kind": str,
    "column": str,
    "start": int,
    "max_steps": int,
    "success": bool,
    "path_length": int,
    "shortest_path": int,
    "collisions": int,
    "last_view_shows_target": bool,
    "episode_length": int,
    "stopped": bool,  # absent in results files written before it was recorded (read as None)
}


def write_results_file(path: Path, text: str | bytes, checksum: bool = False) -> None:
    """Atomically; with `checksum`, its sha256 beside it (results files: an edit is refused, not summed)."""
    try:
        data = text.encode() if isinstance(text, str) else text
        write_with_checksum(path, data) if checksum else atomic_write(path, data)
    except OSError as e:
        raise EvalError(f"cannot write {path}: {e.strerror or e}; choose another --runs folder") from e


# A finished evaluation kept in git (tables/episodes/): its config.json and every episode as one CSV,
# with each kitchen file's sha256, xz-compressed. About 0.5 MB for Table I's 77,100 episodes, a third
# of the folder's own JSON lines compressed; the runs folder that holds the evaluations can be lost.
PACKED_SUFFIX = ".tar.xz"
PACKED_MEMBERS = ("config.json", "episodes.csv", "checksums.json")


def pack_evaluation(directory: Path, out_dir: Path) -> Path:
    """`directory` (a finished evaluation: every kitchen's results present and matching its checksum)
    as OUT_DIR/<its name>.tar.xz, the same bytes every time; `unpack_evaluation` rebuilds its results
    files byte for byte."""
    import csv
    import tarfile

    directory = Path(directory)
    config_bytes = (directory / "config.json").read_bytes() if (directory / "config.json").is_file() else None
    if config_bytes is None:
        raise EvalError(f"{directory} is not an evaluation (no config.json)")
    config = json.loads(config_bytes)["identity"]["config"]
    kitchens = config["kitchens"] or kitchens_of_split(config["split"])  # none listed: all of its split
    table, checksums = io.StringIO(), {}
    writer = csv.writer(table, lineterminator="\n")
    writer.writerow(RESULT_TYPES)
    for kitchen in kitchens:
        path = directory / "episodes" / f"{kitchen}.jsonl"
        data = path.read_bytes() if path.is_file() else b""
        if not data or checksum_matches(path, data) is not True:
            raise EvalError(f"{path} is missing or does not match its checksum: evaluate it first")
        for line in data.decode().splitlines():
            row = json.loads(line)
            writer.writerow(
                "" if row.get(k) is None else int(row[k]) if kind is bool else row[k]
                for k, kind in RESULT_TYPES.items()
            )
        checksums[kitchen] = hashlib.sha256(data).hexdigest()
    members = (config_bytes, table.getvalue().encode(), (json.dumps(checksums, indent=1) + "\n").encode())
    out = Path(out_dir) / f"{directory.name}{PACKED_SUFFIX}"
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w:xz", preset=9) as tar:
        for name, content in zip(PACKED_MEMBERS, members):
            info = tarfile.TarInfo(f"{directory.name}/{name}")  # mtime, owner: 0, so the same bytes
            info.size, info.mode = len(content), 0o644
            tar.addfile(info, io.BytesIO(content))
    write_results_file(out, buffer.getvalue())
    return out


def unpack_evaluation(archive: Path, eval_root: Path) -> Path:
    """Rebuild a packed evaluation in EVAL_ROOT/<its name> (RUNS/eval): its config.json and each
    kitchen's results with their checksums, each checked against the sha256 it was packed with. Files
    already there are kept, never overwritten: a config.json of the same evaluation (its identity; the
    git revision, machine and plugin path it records may differ) stays, another one is refused; a
    kitchen's results file that holds the archive's episodes stays; an intact one (its checksum proves
    it) that holds others is refused (nothing is unpacked: the runs folder and the archive disagree,
    and neither is silently preferred); a damaged one is set aside, as `evaluate` does, and replaced.
    A later evaluation of that config then resumes from them."""
    import csv
    import lzma
    import tarfile

    archive = Path(archive)
    name = archive.name.removesuffix(PACKED_SUFFIX)
    try:
        with tarfile.open(archive, mode="r:xz") as tar:
            members = {m.name: m for m in tar.getmembers()}
            if set(members) != {f"{name}/{m}" for m in PACKED_MEMBERS}:
                raise EvalError(f"{archive} is not a packed evaluation named {name}: holds {sorted(members)}")
            config_bytes, table, checksums = (
                tar.extractfile(members[f"{name}/{m}"]).read() for m in PACKED_MEMBERS
            )
    except (OSError, EOFError, lzma.LZMAError, tarfile.TarError) as e:
        raise EvalError(f"{archive} cannot be read as a packed evaluation: {e}") from e
    checksums = json.loads(checksums)
    directory = Path(eval_root) / name
    config_path = directory / "config.json"
    try:
        packed_identity = json.loads(config_bytes)["identity"]
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as e:
        raise EvalError(f"{archive}: its config.json holds no evaluation's identity ({first_line(e)})") from e
    if config_path.exists():
        try:
            identity = json.loads(config_path.read_bytes())["identity"]
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError):
            identity = None
        if identity != packed_identity:
            raise EvalError(f"{config_path} holds another evaluation than {archive}: nothing unpacked")
    by_kitchen: dict[str, list[str]] = {}
    reader = csv.reader(io.StringIO(table.decode()))
    if tuple(next(reader, ())) != tuple(RESULT_TYPES):
        raise EvalError(f"{archive}: its episodes.csv does not have the fields {', '.join(RESULT_TYPES)}")
    for values in reader:
        row = {
            k: (bool(int(v)) if kind is bool else kind(v))
            for (k, kind), v in zip(RESULT_TYPES.items(), values)
            if v != ""
        }
        by_kitchen.setdefault(row["kitchen"], []).append(json.dumps(row) + "\n")
    if set(by_kitchen) != set(checksums):
        raise EvalError(f"{archive}: its episodes and its checksums name other kitchens")
    rebuilt = {}
    for kitchen, lines in by_kitchen.items():
        data = "".join(lines).encode()
        if hashlib.sha256(data).hexdigest() != checksums[kitchen]:
            raise EvalError(f"{archive}: {kitchen}'s episodes do not rebuild the file that was packed")
        path = directory / "episodes" / f"{kitchen}.jsonl"
        rebuilt[path] = data
        there = _bytes_of(path)
        # checked for every kitchen before any is written: an intact file (its checksum proves it is
        # what was written) with other episodes is another result of the same evaluation
        if there is not None and there != data and checksum_matches(path, there):
            raise EvalError(
                f"{path} holds other episodes than {archive} (the same evaluation, other results: another "
                "machine's or code's floats); nothing unpacked: keep one, delete the other"
            )
    if not config_path.exists():
        write_results_file(config_path, config_bytes)
    for path, data in rebuilt.items():
        there = _bytes_of(path)
        if there == data and checksum_matches(path, there):
            continue  # the archive's episodes, intact: kept
        if there is not None and there != data:
            # damaged (its checksum does not prove it, checked above): set aside, as evaluate does
            aside = path.with_name(f"{path.name}.corrupt-{int(time.time())}")
            path.rename(aside)
            print(
                f"kgnavbench: {path} is damaged; moved to {aside.name}, unpacked from {archive}",
                file=sys.stderr,
            )
        write_results_file(path, data.decode(), checksum=True)  # (its checksum too, where it lacked one)
    return directory


def _bytes_of(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except OSError:
        return None
