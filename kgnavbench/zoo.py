"""Stage 27 — zoo: finished training runs shipped into a folder of their own (`zoo/`), and found there.

`ship_run` copies a finished run (config.json, metrics.csv, finished.json, best.pt and, with "last",
last.pt, weights only, each with its sha256) into the zoo, whole or not at all. `trained_run` finds, in
a zoo or a runs folder, the finished run that a table's job would train (`table --trained DIR`): same
method, options, frames, seed and kitchens, whatever code revision trained it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from . import store
from .files import checksum_matches, first_line, one_line
from .plugins import UNWEIGHTED_OPTIONS
from .runs import (
    POLICY_KEYS,
    TrainError,
    checkpoint_differences,
    load_checkpoint,
    save_checkpoint,
    training_code_sha256,
)
from .table_spec import (
    TableError,
)

# what a run's config.json must share with a row's job to be that job's run in a `trained` folder; the
# code's hashes are left out: a shipped run stays usable after later changes to the training code
# (stacked_seeds: a run of `train --seeds` is none of a table's single-seed jobs, as another world_size)
TRAINED_RUN_KEYS = (
    "method",
    "options",
    "frames",
    "seed",
    "kitchens",
    "world_size",
    "device",
    "stacked_seeds",
)
# options a plugin gained after runs were shipped, with the value that reproduces how those runs
# trained: a shipped run's config without the option is read as having that value
ADDED_OPTIONS = {
    "kg_edges": "binary",
    "kg_readout": "pooled",
    "attention_context": True,
    "attention_heads": 1,
    "gcn_norm": "none",
    "attention_over": "union",
    "attention_bound": 0.0,
}


def record_differences(config: dict, record: dict) -> list[str]:
    """What a run's config.json differs in from a job's `record` on TRAINED_RUN_KEYS ("options.il",
    "frames", ...; none: it is that job's run). An option the run predates counts as ADDED_OPTIONS
    says; UNWEIGHTED_OPTIONS are not compared."""
    differ = [key for key in TRAINED_RUN_KEYS if config.get(key) != record.get(key)]
    if isinstance(config.get("options"), dict) and "options" in differ:
        options = {**{k: v for k, v in ADDED_OPTIONS.items() if k in record["options"]}, **config["options"]}
        differ.remove("options")
        differ += [
            f"options.{k}"
            for k in sorted({*options, *record["options"]} - set(UNWEIGHTED_OPTIONS))
            if options.get(k) != record["options"].get(k)
        ]
    return differ


def trained_run(folder: Path, record: dict, row_name: str, progress=print, unfinished: bool = False) -> Path:
    """The finished run in `folder` (its run folders, or those of its train/) whose config matches
    `record` (`run_record`) on TRAINED_RUN_KEYS (`unfinished`: or the run still training). Trained by
    other code than this checkout's, it is used with a line that says from which revision. Where
    several runs match (a job trained again by newer code beside the old run), the one this
    checkout's training code trained is used; failing that, they are named and none is used, rather
    than one picked by folder name."""
    want = {key: record.get(key) for key in TRAINED_RUN_KEYS}
    nearest: tuple[int, str] | None = None  # (keys that differ, which) of the closest run, for the error
    matches: list[tuple[Path, dict]] = []
    unreadable: list[tuple[Path, str]] = []
    for run_dir, config in _run_configs(folder, record["method"], unreadable):
        differ = record_differences(config, want)
        if differ:
            if nearest is None or len(differ) < nearest[0]:
                nearest = (len(differ), f"{run_dir} differs in {', '.join(differ[:6])}")
            continue
        matches.append((run_dir, config))
    if not matches and unreadable:  # the run may be the damaged one: name it, not another run
        path, why = unreadable[0]
        more = f" (and {len(unreadable) - 1} more)" if len(unreadable) > 1 else ""
        raise TableError(
            f"row {row_name!r} (seed {record['seed']}): no finished {record['method']} run in {folder} "
            f"matches, and {path} is unreadable ({why}){more}: restore it (from git, for zoo/) and run again"
        )
    if not matches:
        hint = f"; the closest, {nearest[1]}" if nearest else ""
        raise TableError(
            f"row {row_name!r} (seed {record['seed']}): no finished {record['method']} run in {folder} "
            f"trained as the preset says{hint}"
        )
    ours = [m for m in matches if m[1].get("training_code_sha256") == record["training_code_sha256"]]
    if len(matches) > 1 and len(ours) != 1:
        named = "; ".join(f"{run_dir} (revision {_revision(config)})" for run_dir, config in matches)
        raise TableError(
            f"row {row_name!r} (seed {record['seed']}): {len(matches)} runs in {folder} trained this job: "
            f"{named}; remove the superseded one(s)"
        )
    run_dir, config = ours[0] if len(matches) > 1 else matches[0]
    if not (run_dir / "finished.json").exists() and not unfinished:
        raise TableError(f"row {row_name!r} (seed {record['seed']}): {run_dir} is not finished")
    return run_dir


def other_code_runs(run_dirs, progress=print) -> None:
    """One line naming the runs among `run_dirs` trained by other training code than this checkout's,
    per revision (a table of the zoo's runs says it once, not once per run): they are used as shipped."""
    ours = training_code_sha256()
    revisions: dict[str, list[str]] = {}
    for run_dir in run_dirs:
        try:
            config = json.loads((Path(run_dir) / "config.json").read_text())
        except (OSError, ValueError):
            continue  # find_trained read it moments ago; a run removed since has nothing to say
        if config.get("training_code_sha256") != ours:
            revisions.setdefault(_revision(config), []).append(Path(run_dir).name)
    if revisions:
        counts = ", ".join(f"{revision} ({len(names)})" for revision, names in sorted(revisions.items()))
        total = sum(map(len, revisions.values()))
        progress(
            f"{total} runs were trained by other training code than this checkout's, by revision: "
            f"{counts}; used as shipped"
        )


def _revision(config: dict) -> str:
    return one_line(str(config.get("git_revision", "?")))[:12]


def _run_configs(folder: Path, method: str, unreadable: list | None = None):
    """(run folder, its config) for each run of `method` in `folder` (its run folders, or those of its
    train/) whose config.json reads as a dict, in order of path; `unreadable` collects the config.json
    of a `method` run folder (by its name) that does not read, with why, so that an error can name it."""
    candidates = sorted(
        path
        for path in {*folder.glob("*/config.json"), *folder.glob("train/*/config.json")}
        if not path.parent.name.startswith(".")  # a staging folder `ship_run` left, never a run
    )
    for config_path in candidates:
        try:
            config = json.loads(config_path.read_text())
            why = None if isinstance(config, dict) else f"a JSON {type(config).__name__}, not a run's config"
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            why = first_line(e)
        if why is not None:  # not a run's config: nothing to match; named if the folder is a method's run
            if unreadable is not None and config_path.parent.name.startswith(f"{method}-"):
                unreadable.append((config_path, why))
            continue
        if config.get("method") == method:
            yield config_path.parent, config


def same_job_runs(zoo: Path, run_dir: Path) -> list[Path]:
    """The other run folders in `zoo` that trained the same job as `run_dir` (equal on
    TRAINED_RUN_KEYS, whatever code trained them): what a retrained run supersedes."""
    config = json.loads((run_dir / "config.json").read_text())
    want = {key: config.get(key) for key in TRAINED_RUN_KEYS}
    return [
        other
        for other, theirs in _run_configs(zoo, want["method"])
        if other != run_dir and not record_differences(theirs, want)
    ]


# a training run's folder: METHOD-HASH as `runs.run_directory` names it (printable ASCII only)
RUN_FOLDER = re.compile(r"[A-Za-z0-9_+][A-Za-z0-9_.+-]*-[0-9a-f]{10}")
# finished.json last: a staging folder left by a killed ship is never a finished run
SHIPPED_FILES = ("config.json", "metrics.csv", "finished.json")


@dataclass(frozen=True)
class Shipped:
    """A run shipped into a zoo: its folder and what zoo/README.md lists of it."""

    folder: Path
    method: str
    seed: int
    frames: int  # trained
    best_frames: int  # best.pt's


def _shipped_checkpoint(path: Path) -> dict:
    """The weights-only copy of a run's checkpoint (POLICY_KEYS), or a TableError naming the file."""
    if path.is_file() and checksum_matches(path, path.read_bytes()) is None:
        raise TableError(f"checkpoint {path} has no checksum ({path.name}.sha256); not shipped")
    try:
        ck = load_checkpoint(path)
    except TrainError as e:
        raise TableError(f"{first_line(e).split('; delete')[0]}; not shipped") from e
    missing = [key for key in POLICY_KEYS if key not in ck]
    if missing:
        raise TableError(f"checkpoint {path} has no {', '.join(missing)}; not shipped")
    return {key: ck[key] for key in POLICY_KEYS}


def ship_run(run_dir: Path, zoo: Path, checkpoints: tuple[str, ...] = ("best",)) -> Shipped:
    """Copy a finished training run into `zoo` (one folder, named as the run) as `--trained` and
    `eval --run` read it: config.json, metrics.csv, finished.json and each checkpoint (best.pt, Table
    I's; last.pt with "last") weights-only, as trained (fp32), with its sha256. A checkpoint without its
    checksum, or one that does not match it, is refused, as is a run whose JSON files do not read; the
    folder appears whole or not at all (it is staged in a hidden folder beside it, which `trained_run`
    skips), and an existing one is never replaced."""
    run_dir, zoo = Path(run_dir), Path(zoo)
    if not RUN_FOLDER.fullmatch(run_dir.name):
        raise TableError(
            f"{ascii(run_dir.name)} is not a run folder's name (METHOD-HASH: letters, digits and _.+-, "
            "not first a dot, then a dash and 10 hexadecimal digits); not shipped"
        )
    for name in (*SHIPPED_FILES, *(f"{c}.pt" for c in checkpoints), *(f"{c}.pt.sha256" for c in checkpoints)):
        if (run_dir / name).is_symlink():  # a link could bring any file of the machine into the zoo
            raise TableError(f"{run_dir / name} is a symbolic link; a run's files are shipped as files only")
    if not (run_dir / "config.json").is_file():
        raise TableError(f"{run_dir} is not a training run (no config.json)")
    if not (run_dir / "finished.json").is_file():
        raise TableError(f"{run_dir} is not finished (no finished.json); ship a run once it has finished")
    config = store.read_record(run_dir / "config.json", ("method", "seed"), TableError)
    finished = store.read_record(run_dir / "finished.json", ("frames",), TableError)
    if config["method"] != run_dir.name.rsplit("-", 1)[0]:
        raise TableError(
            f"{run_dir}/config.json names the method {ascii(config['method'])}, not the folder's "
            f"{run_dir.name.rsplit('-', 1)[0]!r}; not shipped"
        )
    frames = finished["frames"]
    if not isinstance(frames, int) or isinstance(frames, bool) or frames < 0:
        raise TableError(
            f"{run_dir}/finished.json's frames {ascii(frames)} is not a whole number; not shipped"
        )
    if not (run_dir / "metrics.csv").is_file():
        raise TableError(f"{run_dir} has no metrics.csv")
    weights = {name: _shipped_checkpoint(run_dir / f"{name}.pt") for name in checkpoints}
    for name, state in weights.items():  # a checkpoint is what its config.json says it is
        differ = checkpoint_differences(state, config)
        if differ:
            raise TableError(
                f"{run_dir / name}.pt is not the run its config.json describes: it differs in "
                f"{'; '.join(differ[:4])}"
            )
    out = zoo / run_dir.name
    if out.exists():
        raise TableError(f"{out} exists; a shipped run is never replaced (delete it first to ship again)")
    zoo.mkdir(parents=True, exist_ok=True)
    for stale in zoo.glob(f".{run_dir.name}-*.tmp"):  # left by a killed ship of this run: never a run
        shutil.rmtree(stale, ignore_errors=True)
    staging = Path(tempfile.mkdtemp(dir=zoo, prefix=f".{run_dir.name}-", suffix=".tmp"))
    try:
        os.chmod(staging, 0o755)  # mkdtemp's folder is private; a zoo folder is read by everyone
        for name, state in weights.items():
            save_checkpoint(staging / f"{name}.pt", state)
        for name in SHIPPED_FILES:
            shutil.copyfile(run_dir / name, staging / name)
        os.rename(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    best = weights["best"]["frames"] if "best" in weights else None
    return Shipped(out, str(config["method"]), config["seed"], finished["frames"], best)
