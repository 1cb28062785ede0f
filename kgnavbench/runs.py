"""Stage 12 — runs: a learned method's options and its run directory.

`TrainOptions` holds every option a learned method shares (a plugin's `Config` extends it; `--set
key=value`). `train_method` resolves a plugin's config into a run directory `runs/train/<method>-<hash>/`
(a hash of the config, the plugin's source, the training code, frames, seed and kitchens), writes
`config.json` once with the git revision, refuses a directory that holds another config, lets one
trainer at a time in (`trainer.claim`), and calls the plugin's `train(config, run)` hook, which for the
shipped methods is `kgnavbench.train.learn`.
"""

from __future__ import annotations

import ast
import contextlib
import csv
import dataclasses
import functools
import hashlib
import io
import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

from . import claims, distributed, store
from .device import DeviceError, name_of, resolve
from .env import SUCCESS_RULES, TRAINING_MAX_STEPS
from .errors import KgnavbenchError
from .files import (
    checksum_matches,
    checksum_path,
    first_line,
    symbolic_link,
    write_with_checksum,
)
from .kitchens import KITCHEN_NAMES, check_name
from .plugins import MAX_SEED, load_plugin
from .tasks import EPISODES_PER_TARGET, N_VAL_KITCHENS, load_task_file

EXPERTS = ("walk_back", "shortest", "dagger")


class TrainError(KgnavbenchError, ValueError):
    """Bad training input or state: a bad option, a run directory holding another config, a corrupt
    checkpoint. Reported as one line."""


# ------------------------------------------------------------------------------------------------
# Options and runs


@dataclass
class TrainOptions:
    """Options every learned method shares (`--set key=value`). A plugin's Config extends this."""

    success_rule: str = "destination"  # the paper's: Stop at the destination; "visible": SAVN's
    # Training episodes treat a wrong Stop as a no-op (evaluation ends the episode): ending them from
    # the start teaches a policy that never succeeded to Stop at once. `stop_ends_from=N` ends them
    # from frame N on; with start_curriculum, N = 0 works (measurements: docs/training.md, "The
    # options' defaults, measured")
    stop_ends_from: int | None = None
    # ... and costs this much more than a step (the paper's rewards otherwise): without it the agent
    # learns that a wrong Stop costs no more than a move, Stops often, and evaluation punishes that
    wrong_stop_penalty: float = 0.0
    # actions per training episode (the task's 5000); shorter episodes mean more of them per frame
    episode_cap: int = TRAINING_MAX_STEPS
    # a curriculum on start distance over this fraction of the run's frames: training episodes start
    # as near the destination as a start can be (no receptacle open, pitch 0), then ever farther (a
    # distance drawn uniformly from 0 to a reach that grows linearly to CURRICULUM_REACH actions; the
    # nearest start below it where none lies at it), then from the training starts as usual. Without
    # imitation the agents otherwise meet too few successes to learn from in a short run: a
    # destination is one state of thousands (measured: docs/training.md). 0 = off
    start_curriculum: float = 0.0
    agents_per_kitchen: int = 64  # agents per training kitchen, all stepped at once
    # each agent keeps one training target (agent j of a kitchen: its target j mod the kitchen's
    # targets), as the paper's "140 threads, each thread learns for a different target"; false: every
    # episode draws a target of the agent's kitchen
    fixed_targets: bool = True
    # with fixed_targets: train only the first N seen targets of each training kitchen (0: all of
    # them). A small task that any sound learner masters quickly (tests/test_train.py)
    targets_per_kitchen: int = 0
    n_steps: int = 20  # rollout length: n-step returns
    lr: float = 7e-4  # Adam
    gamma: float = 0.99
    value_weight: float = 0.5  # alpha: weight of the value loss
    entropy: float = 0.01  # weight of the entropy bonus
    max_grad_norm: float = 10.0
    # bfloat16 autocast (on CUDA always). On a CPU it checks the arithmetic a GPU runs; it is no faster
    # even with native bf16 (AVX512-BF16 or AMX), and without it the products run in ATen's reference
    # kernels, ten times slower (measured: docs/training.md)
    bf16: bool = False
    hidden: int = 256  # siamese / fusion width
    lstm: int = 256
    # imitation learning: cross-entropy on expert trajectories
    il: bool = False
    # "walk_back": the paper's expert, "only one expert trajectory for each training target": from the
    # destination, MoveBack, else MoveLeft, else RotateRight, for a walk of random length, reversed;
    # "shortest": one BFS-optimal path per target from a training start; "dagger": the BFS-optimal
    # actions of every state the agents visit (DAgger with a privileged shortest-path teacher, not the
    # paper's IL: it learns far more, e.g. 91% seen/seen SR against the paper's 8%)
    il_expert: str = "walk_back"
    il_walk: int = 25  # the walk back is 10..il_walk steps long (drawn per target), as the training starts
    # IL is mixed into the loss over this fraction of the run's frames ("online and before a certain
    # number of time steps"), as start_curriculum is a fraction: one meaning for both
    il_fraction: float = 1.0
    il_batch: int = 32  # expert trajectories per update
    il_weight: float = 1.0
    # target skill extension: relabelled sub-trajectories of the agents' own episodes
    tse: bool = False
    tse_subtargets: int = 5  # per episode, sampled at random among the states that show a novel object
    # the seen kitchens' unseen targets may be sub-targets (the paper's "TSE (targets)"): this trains on
    # the seen-kitchens/unseen-targets column's test targets, so it is off by default ("TSE (seen targets)")
    tse_unseen_targets: bool = False
    tse_window: int = 40  # steps before the sub-target that are relabelled
    tse_batch: int = 64  # sub-trajectories per update
    # at 1.0 the relabelled "Stop here, +10" episodes outweigh the rest and the agents learn to Stop
    # anywhere (docs/training.md)
    tse_weight: float = 0.1
    # truncated importance weights min(1, pi/mu) on the relabelled steps. Without them every action of a
    # relabel (mostly ending in +10) is pushed up whatever the current policy thinks of it, and the
    # policy collapses onto its own habits (docs/training.md)
    tse_importance: bool = True
    # a wrong Stop in a sub-target's window is an episode of the relabelled task too, one that failed:
    # "Stop here, short of the sub-target" (-0.01, no +10) trains beside the successful relabel. Without
    # these the relabels only ever reward Stop, and since training's wrong Stop is a no-op the agents
    # learn to Stop everywhere (docs/training.md)
    tse_failures: bool = True
    # logs, checkpoints, validation
    log_every: int = 200_000  # frames between metrics rows (and checkpoints)
    val_every: int = 1_000_000  # frames between validations (and at the end)
    val_kitchens: int = 5  # the first N validation kitchens
    val_episodes: int = 5  # the first N fixed episodes per target
    # frames between kept snapshots of the weights (DIR/snapshots/frames-N.pt, N the frames at which
    # it was taken; `eval --run DIR --checkpoint frames-N`): learning curves. 0: none
    keep_every: int = 0
    threads: int = 2
    # end to end from pixels: the encoder CNN (from the committed weights) trains with the policy on
    # the 84x84 views instead of reading cached features (the GPU path; slow on a CPU)
    pixels: bool = False

    def __post_init__(self) -> None:
        self.check()  # a bad option fails when the config is made, before a run directory exists

    def check(self) -> None:
        if self.success_rule not in SUCCESS_RULES:
            raise TrainError(f"success_rule must be one of {SUCCESS_RULES}, not {self.success_rule!r}")
        if self.success_rule == "arrival":  # (the trainer's navigators take the Stop-based rules only)
            raise TrainError("success_rule 'arrival' is an evaluation rule (Zhu et al.'s): train under "
                             "'destination' or 'visible'")  # fmt: skip
        if self.il_expert not in EXPERTS:
            raise TrainError(f"il_expert must be one of {EXPERTS}, not {self.il_expert!r}")
        positive = (
            "episode_cap agents_per_kitchen n_steps hidden lstm il_batch tse_window tse_batch log_every "
            "val_every val_kitchens val_episodes threads il_walk"
        )
        for name in positive.split():
            if getattr(self, name) < 1:
                raise TrainError(f"{name} must be at least 1, not {getattr(self, name)}")
        bounded = {
            "agents_per_kitchen": MAX_AGENTS_PER_KITCHEN,
            "val_kitchens": N_VAL_KITCHENS,  # there are no more validation kitchens
            "val_episodes": EPISODES_PER_TARGET,  # nor fixed episodes per target
        }
        for name, most in bounded.items():
            if getattr(self, name) > most:
                raise TrainError(f"{name} must be at most {most}, not {getattr(self, name)}")
        if self.targets_per_kitchen < 0 or (self.targets_per_kitchen and not self.fixed_targets):
            raise TrainError("targets_per_kitchen must be 0 (all) or more, and needs fixed_targets=true")
        if not (0 < self.gamma <= 1 and self.lr > 0 and self.max_grad_norm > 0):
            raise TrainError("need 0 < gamma <= 1, lr > 0 and max_grad_norm > 0")
        if min(self.tse_subtargets, self.stop_ends_from or 0, self.keep_every) < 0:
            raise TrainError("tse_subtargets, stop_ends_from and keep_every must not be negative")
        for name in ("start_curriculum", "il_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise TrainError(f"{name} is a fraction of the run, 0 to 1, not {getattr(self, name)}")


MAX_AGENTS_PER_KITCHEN = 1024  # 20,480 agents over the training kitchens: more is a typo (and the memory)


@dataclass(frozen=True)
class Run:
    """Where and how long a plugin's `train` hook trains."""

    directory: Path
    method: str
    frames: int
    seed: int
    kitchens: tuple[str, ...]  # training kitchens (their seen targets only)
    progress: Callable[[str], None] = print
    device: str = "cpu"  # the torch device it trains on (kgnavbench/device.py)
    # `train --seeds`: the runs of the row's other seeds, trained in the same process as this one
    # (`train.learn`: one network with a seed dimension, kgnavbench/stacking.py)
    stacked: tuple[Run, ...] = ()


def training_kitchens(kitchens=()) -> tuple[str, ...]:
    """The training kitchens to train on: all of the split, or the given ones (each must be one)."""
    train = load_task_file()["splits"]["train"]
    if not kitchens:
        return tuple(sorted(train, key=KITCHEN_NAMES.index))
    for k in kitchens:
        check_name(k)
        if k not in train:
            raise TrainError(f"{k} is not a training kitchen (training kitchens: {', '.join(train)})")
    return tuple(dict.fromkeys(kitchens))


# the library code that decides a run's numbers besides the plugin: the training starts and the state
# graphs' semantics, the env's rewards, the models and this trainer (kitchens, world and render reach a
# run through the state-graph cache, which is keyed by their own fingerprint)
TRAINING_CODE = (
    "graph.py", "tasks.py", "encoder.py", "env.py", "vecenv.py", "runs.py", "losses.py", "models.py",
    "agent.py", "rollout.py", "learning.py", "stacking.py", "train.py",
)  # fmt: skip


def training_code_sha256(package: Path = Path(__file__).parent) -> str:
    """A hash of the training code's syntax trees without docstrings, so that a finished run is not
    reused after a change to how runs train, while comments, docstrings and formatting do not count."""
    digest = hashlib.sha256()
    for name in TRAINING_CODE:
        tree = ast.parse((package / name).read_text(), filename=name)
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if (
                isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                and body
                and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)
            ):
                node.body = body[1:] or [ast.Pass()]
        digest.update(f"{name}\0{ast.dump(tree)}\0".encode())
    return digest.hexdigest()


@functools.cache
def imported_training_code_sha256() -> str:
    """`training_code_sha256` of this checkout, computed at a process's first run record and kept:
    files edited while a process runs do not rename its runs (the CLI's commands are one process
    each). In an interpreter that reloads edited training code, call `.cache_clear()`."""
    return training_code_sha256()


def run_record(
    plugin, config, frames: int, seed: int, kitchens: tuple[str, ...], device: str = "cpu", stacked=()
) -> dict:
    """What decides a run: its hash names the run directory. `stacked`: the seeds trained in one
    process with it (`train --seeds`), recorded as torchrun's world_size is (their floats are not a
    single-seed run's); a single seed's record has no such field, so its name is today's."""
    return {
        "method": plugin.name,
        "options": json.loads(json.dumps(asdict(config))),
        "plugin_source_sha256": hashlib.sha256(plugin.source_bytes()).hexdigest(),
        "training_code_sha256": imported_training_code_sha256(),
        "frames": frames,
        "seed": seed,
        "kitchens": list(kitchens),
        "world_size": distributed.from_env().world,  # torchrun's ranks: another number is another run
        "device": device,  # "cpu" or "cuda": their numbers differ, as the threads' do
        **({"stacked_seeds": list(stacked)} if len(stacked) > 1 else {}),
    }


def run_directory(runs_dir: Path | str, record: dict) -> Path:
    return Path(runs_dir) / "train" / f"{record['method']}-{store.digest(record, 10)}"


def train_method(
    method: str,
    options: dict[str, str] | None = None,
    frames: int = 10_000_000,
    seed: int = 0,
    kitchens=(),
    runs_dir: Path | str = "runs",
    progress: Callable[[str], None] = print,
    device: str = "auto",
) -> Path:
    """Train METHOD (or resume its run, or find it finished) on `device` (auto | cpu | cuda) and
    return the run directory."""
    return train_seeds(method, options, frames, (seed,), kitchens, runs_dir, progress, device)[0]


def train_seeds(
    method: str,
    options: dict[str, str] | None = None,
    frames: int = 10_000_000,
    seeds: tuple[int, ...] = (0,),
    kitchens=(),
    runs_dir: Path | str = "runs",
    progress: Callable[[str], None] = print,
    device: str = "auto",
) -> list[Path]:
    """`train_method` for several seeds of one method and options, trained in one process (stacked:
    `train.learn`), each a run of its own; the run directories, in the order of `seeds`. One seed is
    `train_method`'s run. A finished seed is left as it is; the others train together."""
    plugin = load_plugin(method)
    hook = getattr(plugin.module, "train", None)
    if not callable(hook):
        raise TrainError(f"{method} does not train: {plugin.source} defines no train(config, run)")
    if frames < 1:
        raise TrainError(f"frames must be positive, not {frames}")
    for seed in seeds:
        if not 0 <= seed <= MAX_SEED:
            raise TrainError(f"seed must be in 0..{MAX_SEED}, not {seed}")
    if not seeds or len(set(seeds)) != len(seeds):
        raise TrainError(f"seeds must be distinct, at least one: {', '.join(map(str, seeds))}")
    config = plugin.config(options or {})
    kitchens = training_kitchens(kitchens)
    try:
        on = resolve(device)
    except DeviceError as e:
        raise TrainError(str(e)) from e
    records = [run_record(plugin, config, frames, s, kitchens, name_of(on), seeds) for s in seeds]
    directories = [run_directory(runs_dir, r) for r in records]
    main = distributed.from_env().main
    if not main:  # torchrun's other ranks say nothing
        progress = lambda line: None  # noqa: E731
    runs = [
        Run(d, method, frames, s, kitchens, progress, str(on))
        for d, s in zip(directories, seeds)
        if not (d / "finished.json").exists()
    ]
    for d in directories:
        if (d / "finished.json").exists():
            progress(f"{d} is a finished run of {frames:,} frames; nothing to do")
    if not runs:
        return directories
    if not main:  # torchrun's other ranks: rank 0 checks, claims and writes
        call_train(plugin.source, hook, config, runs[0])
        return directories
    # one trainer per run directory: a second one started on it at once is refused (a killed one's
    # claim is stale and taken over by the resume)
    try:
        with contextlib.ExitStack() as held:
            for run in runs:
                held.enter_context(claims.held(run.directory / "trainer.claim", f"run {run.directory}"))
            runs = [r for r in runs if not (r.directory / "finished.json").exists()]  # finished meanwhile
            for run in runs:
                store.open_directory(
                    run.directory, records[directories.index(run.directory)], TrainError, "a run"
                )
            if runs:
                call_train(plugin.source, hook, config, dataclasses.replace(runs[0], stacked=tuple(runs[1:])))
    except claims.ClaimError as e:
        raise TrainError(str(e)) from e
    unfinished = [r.directory for r in runs if not (r.directory / "finished.json").exists()]
    if len(runs) > 1 and unfinished:
        raise TrainError(
            f"{plugin.source}: train() returned without finishing the stacked seeds' runs "
            f"{', '.join(map(str, unfinished))}: its train() does not call kgnavbench.train.learn; "
            "train its seeds one by one"
        )
    return directories


def call_train(source, hook, config, run: Run) -> None:
    """A plugin's train(config, run): what it raises, or a sys.exit, becomes one TrainError naming its
    file (a Ctrl-C stays a KeyboardInterrupt: the run resumes from its last checkpoint)."""
    try:
        hook(config, run)
    except TrainError:
        raise
    except SystemExit as e:
        raise TrainError(f"{source}: train() called sys.exit({e.code!r}); a plugin raises instead") from e
    except Exception as e:  # noqa: BLE001 - a plugin's failure, reported in one line with its file
        raise TrainError(f"{source}: train() failed: {type(e).__name__}: {e}") from e


# ------------------------------------------------------------------------------------------------
# Checkpoints

CHECKPOINT_FORMAT = 1
# what a policy needs of a training checkpoint (policy.load_policy): the weights, their config and the
# knowledge graph's counts; no optimiser, generators or agents. A weight snapshot and a shipped
# checkpoint keep these keys only: about a third of a training checkpoint
POLICY_KEYS = (
    "format", "method", "options", "model_config", "kitchens", "seed", "frames", "updates", "covis", "model",
)  # fmt: skip


# a run stops within one update of its frames (at most 2,800 frames past them in the paper preset)
FRAMES_PAST_THE_RUN = 100_000


def checkpoint_differences(ck: dict, config: dict) -> list[str]:
    """What a checkpoint records that is not the run of `config` (its config.json, `run_record`): its
    method, every option, kitchens and seed, each named with both values, and frames that are not a
    whole number from 0 to the run's frames (FRAMES_PAST_THE_RUN past them at most). Empty when the
    checkpoint is that run's. (+IL+TSE and LSTM A3C share method and model and differ in options.)"""
    out = []
    for key in ("method", "kitchens", "seed"):
        mine, theirs = ck.get(key), config.get(key)
        if key == "kitchens" and isinstance(mine, (list, tuple)) and isinstance(theirs, (list, tuple)):
            mine, theirs = list(mine), list(theirs)
        if mine != theirs:
            out.append(f"{key} {ck.get(key)!r} (config.json: {config.get(key)!r})")
    ck_options, options = ck.get("options"), config.get("options")
    if not isinstance(ck_options, dict) or not isinstance(options, dict):
        out.append("options (not a table of options)")
    else:
        out += [
            f"option {k} {ck_options.get(k)!r} (config.json: {options.get(k)!r})"
            for k in sorted({*ck_options, *options})
            if ck_options.get(k) != options.get(k)
        ]
    frames, limit = ck.get("frames"), config.get("frames")
    if not isinstance(limit, int) or isinstance(limit, bool):
        out.append(f"config.json's frames {limit!r} (not a whole number)")
    elif (
        not isinstance(frames, int)
        or isinstance(frames, bool)
        or not 0 <= frames <= limit + FRAMES_PAST_THE_RUN
    ):
        out.append(f"frames {frames!r} (the run trains {limit:,})")
    return out


def save_checkpoint(path: Path, state: dict) -> None:
    """Write a checkpoint atomically, with its sha256 beside it (PATH.sha256): a crash leaves the old one
    or the new one, never half of one, and a checkpoint changed afterwards is refused when loaded."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_with_checksum(Path(path), buffer.getvalue())


def load_checkpoint(path: Path | str) -> dict:
    """A checkpoint written by `train.learn`; anything else is a TrainError naming the file."""
    path = Path(path)
    linked = symbolic_link(path) or symbolic_link(checksum_path(path))
    if linked:
        raise TrainError(linked)
    try:
        data = path.read_bytes()
    except FileNotFoundError as e:
        raise TrainError(f"checkpoint {path} does not exist") from e
    except OSError as e:
        raise TrainError(f"checkpoint {path} cannot be read ({e.strerror or e})") from e
    if checksum_matches(path, data) is False:
        raise TrainError(
            f"checkpoint {path} is corrupt: it does not match its checksum ({checksum_path(path).name}), "
            "so it changed after it was written; delete both to start over"
        )
    try:
        ck = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        if not isinstance(ck, dict) or ck.get("format") != CHECKPOINT_FORMAT:
            raise ValueError("not a kgnavbench checkpoint")
        for key in ("model", "model_config", "covis", "kitchens", "frames"):
            if key not in ck:
                raise ValueError(f"no {key!r}")
        return ck
    except FileNotFoundError as e:
        raise TrainError(f"checkpoint {path} does not exist") from e
    except Exception as e:  # noqa: BLE001 - whatever is wrong with the file, one line naming it
        raise TrainError(
            f"checkpoint {path} is corrupt ({type(e).__name__}: {first_line(e)}); delete it to start over"
        ) from e


# metrics.csv on resume


def read_metrics_rows(path: Path, up_to: int) -> list[dict]:
    """The rows of metrics.csv up to a frame count (a resumed run drops what it will redo)."""
    if not path.exists():
        return []
    rows = []
    for row in csv.DictReader(path.read_text().splitlines()):
        try:
            if int(row["frames"]) <= up_to and None not in row.values():
                rows.append(row)
        except (KeyError, TypeError, ValueError):
            continue
    return rows


def seconds_at(rows: list[dict], frames: int) -> float | None:
    """The training time metrics.csv's rows give at a frame count (a resume point), if one does."""
    for row in reversed(rows):
        try:
            if int(row["frames"]) == frames:
                seconds = float(row.get("seconds") or "nan")
                return seconds if math.isfinite(seconds) and seconds >= 0 else None
        except (KeyError, ValueError):
            return None
    return None
