"""Stage 21 — weights: which weights an evaluation tests. A training run's checkpoints (`best`: Table
I's rule, the highest validation SR; `last`: the final weights; `frames-N`: a snapshot kept with
keep_every), chosen (`selected_checkpoint`), read once and checked against the checkpoint's own record
(`read_weights`), and frozen into the evaluation's own directory (`freeze_weights`). `EvalError` is
every evaluation stage's error.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

from .errors import KgnavbenchError
from .files import (
    atomic_write,
    checksum_matches,
    checksum_path,
    first_line,
    sha256_file,
    symbolic_link,
    write_with_checksum,
)

# a training run's checkpoints that `eval --run` can test
CHECKPOINT_MEANING = {"best": "best validation SR", "last": "the run's latest weights"}
CHECKPOINTS = tuple(CHECKPOINT_MEANING)
SNAPSHOT = re.compile(r"frames-[0-9]{1,15}")  # a kept snapshot (train's keep_every): snapshots/frames-N.pt


def checkpoint_name(name: str) -> str:
    """best, last or frames-N (a snapshot); anything else is an EvalError."""
    if name in CHECKPOINTS or SNAPSHOT.fullmatch(name):
        return name
    raise EvalError(f"unknown checkpoint {name!r}; choose one of {CHECKPOINTS} or frames-N (a kept snapshot)")


class EvalError(KgnavbenchError, ValueError):
    """Bad evaluation input: unknown split or kitchen, a corrupt results file."""


@dataclass
class Weights:
    """A run's selected checkpoint as one evaluation tests it: read once, its bytes and their sha256."""

    source: Path
    data: bytes
    sha256: str


def read_weights(run: str | Path, method: str, which: str = "best") -> Weights:
    """The selected checkpoint (`which`) of the training run `run`, read once: every kitchen of an
    evaluation gets these bytes (a trainer that replaces best.pt meanwhile changes nothing), and its
    sha256 is the evaluation's identity. The checkpoint's own record must name the method (config.json
    may be relabelled; the weights are what they are)."""
    trained_config = run_config(run)  # one read: the method's check and the identity's compare
    source = selected_checkpoint(run, method, which, trained_config)
    try:
        data = source.read_bytes()
    except OSError as e:
        raise EvalError(f"cannot read {source}: {e.strerror or e}") from e
    import torch  # only where a trained method is evaluated (the command line starts without it)

    from .runs import checkpoint_differences

    try:
        record = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        trained = record.get("method")
    except Exception as e:  # noqa: BLE001 - whatever is wrong with the file, one line naming it
        raise EvalError(f"checkpoint {source} is corrupt ({type(e).__name__}: {first_line(e)})") from e
    matches = checksum_matches(source, data)
    if matches is False:
        raise EvalError(f"checkpoint {source} does not match its checksum: it changed after it was written")
    others = [p for p in (source.with_name("best.pt"), source.with_name("last.pt")) if p != source]
    if (
        matches is None
        and (Path(run) / "finished.json").exists()
        and any(checksum_path(p).exists() for p in others)
    ):
        # a finished run whose other checkpoint has its checksum wrote this one with its own too, and
        # `ship` copies both: one without is a file nobody can vouch for. (An unfinished run's last.pt
        # may lack one, a writer killed between the two files; a run from before checksums has none.)
        raise EvalError(
            f"checkpoint {source} has no checksum ({source.name}.sha256) although the run is finished: "
            "restore the checksum with the weights it was written with (from git, for zoo/)"
        )
    if trained != method:
        raise EvalError(f"{source} holds weights trained by {trained!r} (its own record), not {method!r}")
    # a checkpoint is what it says it is: its own record of options, kitchens, seed and frames must
    # be the run's config.json's (+IL+TSE's weights in an LSTM A3C run share method and model)
    differ = checkpoint_differences(record, trained_config)
    if differ:
        raise EvalError(
            f"{source} is not the run its config.json describes: it differs in {'; '.join(differ[:4])}"
        )
    role = checkpoint_role_problem(Path(run), which, record)
    if role:
        raise EvalError(f"{source} is not the run's {which} checkpoint: {role}")
    return Weights(source, data, hashlib.sha256(data).hexdigest())


def checkpoint_role_problem(directory: Path, which: str, record: dict) -> str | None:
    """What the checkpoint records against the role its name gives it (None: they agree): a snapshot
    frames-N holds frame N's weights; a finished run's last.pt its final frame's; its best.pt those of
    its highest validation SR in its own metrics.csv, ties to the later (runs finished under this rule
    say so in finished.json; four zoo runs have it at their last frame, rightly). A file copied over
    another with its checksum redone is caught here, not by the checksum."""
    frames = record.get("frames")
    if SNAPSHOT.fullmatch(which):
        named = int(which.split("-", 1)[1])
        return None if frames == named else f"it holds the weights of frame {frames}, not of frame {named}"
    try:
        finished = json.loads((directory / "finished.json").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None  # an unfinished run: its best and last move on
    if not isinstance(finished, dict):
        return None
    if which == "last":
        final = finished.get("frames")
        return (
            None if frames == final else f"it holds the weights of frame {frames}, the run ended at {final}"
        )
    if "best_rule" not in finished:  # finished before the rule was written down: another rule chose
        return None
    try:
        with open(directory / "metrics.csv", newline="") as f:
            validated = [(float(r["val_sr"]), int(r["frames"])) for r in csv.DictReader(f) if r.get("val_sr")]
    except (OSError, UnicodeDecodeError, KeyError, ValueError, csv.Error):
        return None  # no readable record to check it against (the run's other checks name a damaged one)
    if not validated:
        return None
    expected = max(validated)[1]  # the highest SR, ties to the later frame
    if frames != expected:
        return (
            f"it holds the weights of frame {frames}, but the run's highest validation SR "
            f"({max(validated)[0]:.2f}%) was at frame {expected} (its metrics.csv)"
        )
    return None


def freeze_weights(directory: Path, weights: Weights) -> Path:
    """The evaluation's own copy of the weights it tests, `weights.pt` in its directory, with its
    sha256 beside it: the record of which weights gave these results, and what every kitchen loads. A
    hard link where the file system allows it and the source still holds those bytes (the trainer
    replaces checkpoints by renaming, so the link keeps them), else a copy of the bytes read."""
    path = directory / "weights.pt"
    if path.exists() and sha256_file(path) == weights.sha256:
        return path
    link = path.with_name(".weights.pt.link")
    try:
        link.unlink(missing_ok=True)
        os.link(weights.source, link)
        if sha256_file(link) != weights.sha256:
            raise OSError("the checkpoint changed since it was read")
        os.replace(link, path)
        atomic_write(checksum_path(path), f"{weights.sha256}  {path.name}\n")
    except OSError:
        link.unlink(missing_ok=True)
        try:
            write_with_checksum(path, weights.data)
        except OSError as e:
            raise EvalError(f"cannot write {path}: {e.strerror or e}; choose another --runs folder") from e
    return path


def run_config(run: str | Path) -> dict:
    """A training run's config.json, read once (a symbolic link or an unreadable file: one line)."""
    directory = Path(run)
    if symbolic_link(directory / "config.json"):
        raise EvalError(symbolic_link(directory / "config.json"))
    try:
        record = json.loads((directory / "config.json").read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise EvalError(f"--run {directory} is not a training run (no readable config.json)") from e
    if not isinstance(record, dict):
        raise EvalError(f"--run {directory} is not a training run (its config.json is not a table)")
    return record


def selected_checkpoint(
    run: str | Path, method: str, which: str = "best", record: dict | None = None
) -> Path:
    """Table I's rule: the checkpoint with the best validation SR (`best.pt` of a training run); with
    `which="last"`, the run's latest (`last.pt`, the final weights of a finished run). The run must be
    one of `method` (its config.json, or `record` read from it, says which)."""
    directory = Path(run)
    trained = (record if record is not None else run_config(directory)).get("method")
    if trained != method:
        raise EvalError(f"--run {directory} trained {trained!r}, not {method!r}")
    which = checkpoint_name(which)
    path = directory / (f"snapshots/{which}.pt" if SNAPSHOT.fullmatch(which) else f"{which}.pt")
    linked = symbolic_link(path) or symbolic_link(checksum_path(path))
    if linked:
        raise EvalError(linked)
    if not path.exists():
        if SNAPSHOT.fullmatch(which):
            kept = sorted(p.stem for p in (directory / "snapshots").glob("frames-*.pt"))
            raise EvalError(f"--run {directory} kept no snapshot {which} (kept: {', '.join(kept) or 'none'})")
        if (directory / "finished.json").exists():  # a shipped run: it will never have one
            raise EvalError(
                f"the run {directory} is finished and has no {path.name}: it was shipped without it, or "
                f"the file was removed (`kgnavbench ship RUN_DIR{' --last' if which == 'last' else ''}` "
                "from the run's own folder ships it)"
            )
        when = "at the first validation" if which == "best" else "at the first checkpoint"
        raise EvalError(f"the run {directory} has no {path.name} yet (it is saved {when})")
    return path
