"""The command line's arguments (kgnavbench/cli.py's): each subcommand's own builder (`eval_arguments`,
`table_arguments`, ...: the parser of one command, its options grouped with their help, as Sample
Factory's argument builders), the options several share (`runs_option`, `device_option`), and the value
types and input checks, each failing with a UsageError: one `kgnavbench: error: ...` line and exit status
2, before any work starts. A helper without a stage number."""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

from .errors import KgnavbenchError
from .evaluate import SPLITS
from .kitchens import KITCHEN_NAMES, check_name
from .plugins import MAX_SEED
from .table_spec import load_spec
from .tasks import EPISODES_PER_TARGET
from .walk import MAX_SIZE, MIN_SIZE
from .weights import checkpoint_name
from .world import ACTIONS


class UsageError(KgnavbenchError):
    """Bad command-line input: reported as one `kgnavbench: error: ...` line, exit status 2."""


class Parser(argparse.ArgumentParser):
    """argparse that raises instead of printing usage and exiting, so `main` reports every error alike."""

    def error(self, message: str):
        raise UsageError(f"{message} (see `{self.prog} --help`)")


def kitchen_list(text: str | None) -> list[str]:
    """`--kitchens A,B`: every name known, none twice, none empty; no option: all 30."""
    if text is None:
        return list(KITCHEN_NAMES)
    names = [k.strip() for k in text.split(",")]
    if not text.strip() or any(not k for k in names):
        raise UsageError(
            f"bad --kitchens {text!r}: expected comma-separated kitchens like FloorPlan1,FloorPlan5"
        )
    twice = sorted({k for k in names if names.count(k) > 1})
    if twice:
        raise UsageError(f"bad --kitchens {text!r}: {', '.join(twice)} named twice")
    return [check_name(k) for k in names]


def json_safe(value):
    """NaN and infinities (a cell without episodes) as JSON's null: `--json` is strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def integer_in(text: str, low: int, high: int) -> int:
    """An integer option's value, low..high (argparse reports the error with the option's name)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not low <= n <= high:
        raise argparse.ArgumentTypeError(f"{n} is not in {low}..{high}")
    return n


def view_size(text: str) -> int:
    """`walk --size`: pixels, MIN_SIZE..MAX_SIZE."""
    return integer_in(text, MIN_SIZE, MAX_SIZE)


def positive(text: str) -> int:
    return integer_in(text, 1, 256)


def seconds(text: str) -> float:
    """A time limit in seconds: a finite number above 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text} is no time limit (a number of seconds above 0)")
    return value


def seed(text: str) -> int:
    return integer_in(text, 0, MAX_SEED)


def seed_list(text: str) -> tuple[int, ...]:
    """'2,0,1' -> (0, 1, 2): distinct seeds, sorted. A stacked job's seeds are part of its runs' names
    (`runs.run_record`'s stacked_seeds), so the same seeds in another order must be the same job, not
    a second training into new run folders with the same weights."""
    seeds = tuple(seed(part.strip()) for part in text.split(","))
    if len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"{text!r}: a seed appears twice")
    return tuple(sorted(seeds))


def writable_folder(path: Path, what: str) -> None:
    """Make the folder (and its parents) or say in one line why it cannot be: before any work starts,
    not after minutes of training."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise UsageError(f"{what} {str(path)!r}: cannot write there ({e.strerror or e})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {str(path)!r}: cannot write there (no permission)")


def writable_file(path: Path, what: str) -> None:
    """The file's folder must exist and be writable, and the file itself, if it exists."""
    folder = path.parent
    if path.is_dir():
        raise UsageError(f"{what} {str(path)!r} is a folder, not a file")
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {str(path)!r}: its folder {str(folder)!r} is missing or not writable")
    if path.exists() and not os.access(path, os.W_OK):
        raise UsageError(f"{what} {str(path)!r} is not writable")


def device_name(name: str) -> str:
    """--device resolved to what a run records: "cpu" or "cuda" (a UsageError where it cannot be)."""
    from .device import DeviceError, name_of, resolve

    try:
        return name_of(resolve(name))
    except DeviceError as e:
        raise UsageError(str(e)) from e


def frames(text: str) -> int:
    """A frame count: an integer, underscores or a k/M suffix allowed (2M, 500k, 2_000_000)."""
    scale = {"k": 1_000, "m": 1_000_000}.get(text[-1:].lower(), 1)
    try:
        n = round(float((text[:-1] if scale > 1 else text).replace("_", "")) * scale)
    except (ValueError, OverflowError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a frame count (e.g. 2000000, 2M, 500k)") from None
    if not 1 <= n <= 10**12:
        raise argparse.ArgumentTypeError(f"{text} is not in 1..10^12 frames")
    return n


def episodes(text: str) -> int:
    return integer_in(text, 1, EPISODES_PER_TARGET)


# ----------------------------------------------------------------------------------------------------
# Each subcommand's arguments (cli.build_parser gives each its command)


def runs_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=Path, default=Path("runs"), help="runs directory (default runs/)")


def preset_options(p: argparse.ArgumentParser, default: str, what: str) -> None:
    """--preset (one of the spec's, listed from the default spec where it reads), --spec and --runs."""
    try:
        names = " | ".join(load_spec().presets)
    except (KgnavbenchError, OSError):  # a damaged default spec is reported when a command reads it
        names = "a preset of the spec"
    p.add_argument("--preset", default=default, help=f"{what}: {names} (default {default})")
    p.add_argument("--spec", type=Path, help="table spec (default tables/table1.toml)")
    runs_option(p)


def seed_option(p: argparse.ArgumentParser, what: str, default: int | None = 0) -> None:
    """--seed; default=None where a command must tell a given --seed 0 from none (`train`: not with
    --seeds), the command then taking 0 for None."""
    p.add_argument("--seed", type=seed, default=default, help=f"seed of {what} (default 0)")


def device_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device",
        default="auto",
        metavar="auto|cpu|cuda",
        help="where torch computes (default auto: CUDA where there is a GPU, else the CPU); a run "
        "records it, since CUDA's numbers are not the CPU's",
    )


def kitchens_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench kitchens`'s arguments."""
    p = sub.add_parser(
        "kitchens",
        help="list the kitchens, or one kitchen's objects",
        description="Without NAME: the 30 kitchens with their reachable cells, objects, hidden objects and "
        "openable receptacles. With NAME: that kitchen's objects (id, type, parent receptacle, hidden).",
    )
    p.add_argument("name", nargs="?", metavar="NAME", help="a kitchen, FloorPlan1 .. FloorPlan30")
    p.add_argument("--json", action="store_true", help="print JSON (a list of objects) instead of a table")
    return p


def walk_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench walk`'s arguments."""
    p = sub.add_parser(
        "walk",
        help="walk the agent through a kitchen, printing what it sees",
        description="Step the agent through a kitchen and print, per step, the action, whether it "
        "succeeded, the pose, the open receptacle and the visible objects. Stop is stepped like any "
        "other action (the walk goes on).",
    )
    p.add_argument("--kitchen", required=True, metavar="NAME", help="FloorPlan1 .. FloorPlan30")
    p.add_argument(
        "--actions",
        required=True,
        metavar="A,B,...",
        help=f"comma-separated actions ({', '.join(ACTIONS)}) and/or random:N for N random actions",
    )
    p.add_argument(
        "--start",
        metavar="X,Z,HEADING,PITCH",
        help="start pose in metres and degrees (default: the world's initial pose)",
    )
    seed_option(p, "the random actions")
    p.add_argument(
        "--placement-seed",
        type=int,
        default=None,
        metavar="S",
        help="re-place movable objects with one of the kitchen's real placements chosen by S "
        "(default: the AI2-THOR start scene)",
    )
    p.add_argument(
        "--size",
        type=view_size,
        default=300,
        help=f"view size in pixels, {MIN_SIZE}..{MAX_SIZE} (default 300)",
    )
    p.add_argument("--out", type=Path, metavar="DIR", help="write view_NNN.png per step and map.png here")
    p.add_argument("--json", action="store_true", help="print one JSON object per step instead of a table")
    return p


def prepare_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench prepare`'s arguments."""
    p = sub.add_parser(
        "prepare",
        help="build and cache the state graphs and 84x84 views of the kitchens",
        description="Build every kitchen's state graph (transitions, visibility, views) into the cache "
        "($KGNAVBENCH_CACHE, else ~/.cache/kgnavbench). Other commands build what they need on first "
        "use; this does it up front, one process per core.",
    )
    p.add_argument("--kitchens", metavar="A,B", help="comma-separated kitchens (default: all 30)")
    p.add_argument("--workers", type=positive, default=None, help="processes (default: one per core)")
    return p


def targets_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench targets`'s arguments."""
    p = sub.add_parser(
        "targets",
        help="a kitchen's targets: kind, seen or unseen, destination, episodes",
        description="The targets of one kitchen with their kind (static/actionable), whether they are "
        "training (seen) targets, their destination pose and the receptacle open there.",
    )
    p.add_argument("name", metavar="NAME", help="a kitchen, FloorPlan1 .. FloorPlan30")
    p.add_argument("--json", action="store_true", help="print JSON")
    return p


def methods_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench methods`'s arguments."""
    p = sub.add_parser("methods", help="list the baseline plugins", description="List the plugins.")
    return p


def eval_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench eval`'s arguments."""
    p = sub.add_parser(
        "eval",
        help="evaluate one method on the fixed episodes and print the Table I layout",
        description="Run a method's plugin over the fixed evaluation episodes (the same for every "
        "method) and print SR, SPL, their L>=5 buckets, collisions, last-view rate and episode length "
        "per Table I column and target kind. Results go to RUNS/eval/<run name>/; rerunning the same "
        "evaluation resumes from the kitchens already saved there.",
    )
    p.add_argument("--method", required=True, metavar="NAME", help="a plugin (see `kgnavbench methods`)")
    p.add_argument(
        "--success-rule",
        choices=("destination", "visible", "arrival"),
        default="destination",
        help="success = Stop at the target's destination, the paper's rule (default), or anywhere the "
        "target is visible (SAVN's), or arriving at the destination by any action, Stop a no-op "
        "(Zhu et al. 2017's; implies --stop-noop)",
    )
    p.add_argument("--stop-noop", action="store_true", help="a Stop that does not succeed is a no-op")
    p.add_argument("--split", choices=SPLITS, default="table", help="table = train + test kitchens (default)")
    p.add_argument("--kitchens", metavar="A,B", help="only these kitchens (default: all of the split)")
    p.add_argument(
        "--episodes",
        type=episodes,
        default=EPISODES_PER_TARGET,
        metavar="N",
        help=f"the first N fixed episodes of every target (default {EPISODES_PER_TARGET})",
    )
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="a plugin option (repeatable)")
    seed_option(p, "the policy")
    runs_option(p)
    p.add_argument(
        "--run",
        type=Path,
        metavar="DIR",
        help="a learned method's training run (its best-validation checkpoint)",
    )
    p.add_argument(
        "--checkpoint",
        type=checkpoint_name,
        default="best",
        metavar="{best,last,frames-N}",
        help="which of the run's checkpoints: best.pt, the best validation SR (Table I's rule, default), "
        "last.pt, its latest weights (the final ones of a finished run), or frames-N, a snapshot kept "
        "with keep_every",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--record", type=Path, metavar="FILE.rrd", help="also record episodes with rerun")
    p.add_argument(
        "--video",
        type=Path,
        metavar="FILE.mp4",
        help="also write the recorded episodes (--record-episodes) as a video: the view and the target "
        "image beside the top-down map, the action in its caption",
    )
    p.add_argument(
        "--step-timeout",
        type=seconds,
        metavar="SECONDS",
        help="end the evaluation with one line if a policy's act() (or reset, make_policy) has not "
        "returned within SECONDS; without it, kgnavbench says every minute which kitchen and step it "
        "is waiting on",
    )
    p.add_argument(
        "--record-episodes",
        type=positive,
        default=2,
        metavar="N",
        help="episodes to record (default 2)",
    )
    p.add_argument(
        "--record-steps",
        type=frames,
        metavar="N",
        help="end each recorded episode after N actions (default: the evaluation's cap)",
    )
    device_option(p)
    return p


def train_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench train`'s arguments."""
    p = sub.add_parser(
        "train",
        help="train a learned method on the training kitchens' seen targets",
        description="Train a learned plugin (one with a train hook) into RUNS/train/<method>-<hash>/: "
        "config.json (with the git revision), metrics.csv, last.pt and best.pt (best validation SR). The "
        "same command resumes a killed run from last.pt and does nothing for a finished one. The last "
        "line printed is the run directory.",
    )
    p.add_argument(
        "--method", required=True, metavar="NAME", help="a learned plugin (see `kgnavbench methods`)"
    )
    p.add_argument(
        "--preset",
        metavar="NAME",
        help="train under a Table I preset's protocol (quick, paper, ... of the spec): its options "
        "(--set's win), frames and kitchens; for one seed (--seed, default 0, or one --seeds) the run is "
        "the one `kgnavbench table` trains for a row with the same options and seed. Several --seeds "
        "train stacked runs, runs of their own that the table does not reuse (it trains one run per "
        "seed). Without --preset: the plugin's own defaults, 10M frames",
    )
    p.add_argument(
        "--spec", type=Path, help="the table spec --preset comes from (default tables/table1.toml)"
    )
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="a training option (repeatable)")
    p.add_argument(
        "--frames",
        type=frames,
        help="frames (agent steps) to train (default: the preset's, else 10,000,000)",
    )
    seed_option(p, "the run: its weights, agents and episodes", default=None)
    p.add_argument(
        "--seeds",
        type=seed_list,
        metavar="S,S,...",
        help="train these seeds (in any order: they are sorted) in one process, their networks stacked "
        "into one, each a stacked run of its own (config.json's stacked_seeds), not the run of that "
        "seed that --seed or `kgnavbench table` trains. Measured no faster on a CPU: 3 seeds stacked "
        "made 0.97x (+IL+TSE) and 0.95x (+KG+Attention) the frames/s of one seed alone (paper preset, "
        "docs/speed.md), so on a CPU train seeds as separate processes; not measured on a GPU. One "
        "seed is --seed's run",
    )
    p.add_argument("--kitchens", metavar="A,B", help="only these training kitchens (default: all 20)")
    runs_option(p)
    p.add_argument("--record", type=Path, metavar="FILE.rrd", help="record the training curves with rerun")
    device_option(p)
    return p


def figures_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench figures`'s arguments."""
    p = sub.add_parser(
        "figures",
        help="the paper's figures from a Table I preset's runs (PNG)",
        description="Collisions per episode and last-view-shows-target rate on unseen kitchens per "
        "method, a t-SNE of the KG model's third GCN layer, and the training curves, from the runs of "
        "`kgnavbench table --preset PRESET` (missing runs are trained and evaluated first; with "
        "--trained DIR, the trained runs come from DIR and a missing one is an error, never trained).",
    )
    preset_options(p, "quick", "the table preset whose runs to draw")
    p.add_argument(
        "--trained",
        type=Path,
        metavar="DIR",
        help="take the preset's trained runs from DIR (zoo/), as `table --trained` does: evaluate what "
        "is not evaluated in --runs, never train",
    )
    p.add_argument(
        "--row",
        action="append",
        metavar="NAME",
        help="only this row of the preset, as named in the spec (repeatable): the others are neither "
        "trained, evaluated nor drawn, and the figures go to OUT/partial/, never over the whole preset's",
    )
    p.add_argument(
        "--curves-only",
        action="store_true",
        help="draw only training_curves_seeds.png (and its CSV) in OUT: validation and training-episode SR "
        "over frames, every seed of each trained row (of --row's rows, if given) that --trained holds, "
        "nothing trained or evaluated; a seed not there is left out with a note",
    )
    device_option(p)
    p.add_argument("--out", type=Path, default=Path("docs/figures"), help="output folder (docs/figures)")
    return p


def ship_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench ship`'s arguments."""
    p = sub.add_parser(
        "ship",
        help="copy a finished training run into zoo/, weights only, for `eval --run` and `table --trained`",
        description="Copy a finished run (RUNS/train/<method>-<hash>/) into ZOO/<method>-<hash>/: "
        "config.json, metrics.csv, finished.json and best.pt (Table I's checkpoint; with --last also "
        "last.pt), each checkpoint weights-only, as trained (fp32), with its sha256. Prints the "
        "folder's size and what zoo/README.md lists of it. Never replaces a folder already there.",
    )
    p.add_argument("run", type=Path, metavar="RUN_DIR", help="a finished training run")
    p.add_argument("--zoo", type=Path, default=Path("zoo"), help="where shipped runs live (default zoo/)")
    p.add_argument("--last", action="store_true", help="also ship last.pt, the final weights")
    return p


def episodes_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench episodes`'s arguments."""
    p = sub.add_parser(
        "episodes",
        help="keep finished evaluations in one small file each (tables/episodes/), or rebuild them",
        description="--pack: each finished evaluation folder (RUNS/eval/<name>/) as OUT/<name>.tar.xz, "
        "its config.json and every episode as one CSV with each kitchen file's sha256 (about 0.5 MB "
        "for Table I's 77,100 episodes). --unpack: rebuild each archive in RUNS/eval/, byte for byte, "
        "so that `table` counts those results instead of evaluating again; files already there are kept.",
    )
    mode = p.add_mutually_exclusive_group(required=True)
    mode.add_argument("--pack", type=Path, nargs="+", metavar="EVAL_DIR", help="finished evaluations")
    mode.add_argument("--unpack", type=Path, nargs="+", metavar="ARCHIVE", help="packed evaluations")
    p.add_argument("--out", type=Path, default=Path("tables/episodes"), help="--pack's folder")
    p.add_argument("--runs", type=Path, default=Path("runs"), help="--unpack's runs folder (default runs/)")
    return p


def checkpoints_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench checkpoints`'s arguments."""
    p = sub.add_parser(
        "checkpoints",
        help="evaluate every kept snapshot of the preset's finished runs into one CSV (and a figure)",
        description="For each finished run of the preset's learned rows in the runs folder: evaluate "
        "each snapshot it kept (keep_every) on the table's fixed episodes, a few per target, and merge "
        "one line per snapshot (validation SR, each cell's SR and SPL) into the CSV, so that any "
        "checkpoint rule can be replayed without training. Run it when a run finishes: its snapshots "
        "are not shipped.",
    )
    preset_options(p, "paper", "the spec's preset whose runs to read")
    p.add_argument("--episodes", type=positive, default=5, help="episodes per target (default 5)")
    p.add_argument("--row", action="append", metavar="NAME", help="only this row (repeatable)")
    p.add_argument(
        "--seed",
        action="append",
        type=seed,
        metavar="S",
        help="only this seed's runs (repeatable): two processes, two seeds, one CSV",
    )
    p.add_argument(
        "--unfinished",
        action="store_true",
        help="also evaluate the snapshots kept so far by runs still training (no line until they finish)",
    )
    p.add_argument("--csv", type=Path, help="default: tables/checkpoints-<preset>.csv")
    p.add_argument("--figure", type=Path, help="also draw validation against each column over frames")
    p.add_argument(
        "--matched",
        action="store_true",
        help="also compare the spec's pairs of rows at the same frames (every snapshot both kept), "
        "other - base per cell with its 95%% interval, into CSV-matched.csv (and FIGURE-matched.png)",
    )
    device_option(p)
    return p


def view_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench view`'s arguments."""
    p = sub.add_parser(
        "view",
        help="open a recording (.rrd) in the rerun viewer",
        description="Open FILE.rrd in the rerun viewer; without a display, say how to watch it.",
    )
    p.add_argument("file", type=Path, metavar="FILE.rrd")
    return p


def table_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench table`'s arguments."""
    p = sub.add_parser(
        "table",
        help="regenerate the paper's Table I from the table spec (train, select, evaluate, write)",
        description="For each row of the table spec: train unless a finished run with the same config "
        "exists (an unfinished one resumes), take the checkpoint with the best validation SR, evaluate "
        "it on the fixed episodes, then write table1.md/.csv/.tex and print the table. Killed and "
        "re-run, it continues where it stopped.",
    )
    preset_options(p, "quick", "the spec's preset")
    p.add_argument("--out", type=Path, help="where the tables go (default: the spec's folder, tables/)")
    p.add_argument(
        "--workers",
        type=positive,
        help="jobs (row x seed) run at once, each in its own process (default: one per core); the "
        "table is the same for any number, only the wall time differs; not with --ray (the cluster's "
        "CPUs decide)",
    )
    many = p.add_mutually_exclusive_group()
    many.add_argument(
        "--jobs",
        action="store_true",
        help="print one command per job (row x seed) and exit, for many machines",
    )
    many.add_argument("--job", type=int, metavar="N", help="run job N of --jobs' list only (no table)")
    many.add_argument(
        "--ray",
        metavar="ADDRESS",
        help="run every job as a task on the Ray cluster at ADDRESS (as ray.init takes it: HOST:PORT, "
        "or auto), then assemble the table; the runs folder must be the same path on every node "
        "(docs/scaling.md); needs kgnavbench[ray]",
    )
    p.add_argument(
        "--ray-node-ip",
        metavar="IP",
        help="this machine's address on the Ray cluster, where Ray would guess another (a cluster on "
        "loopback addresses)",
    )
    p.add_argument(
        "--trained",
        type=Path,
        metavar="DIR",
        help="take every trained run from DIR (zoo/, or another runs folder) and only evaluate and "
        "assemble: a run there counts when its method, options, frames, seed and kitchens are the "
        "preset's, whatever code revision trained it; a missing one is an error, never trained",
    )
    p.add_argument(
        "--against",
        metavar="PRESET",
        help="also assemble PRESET's table of the same runs and episodes (paper against paper-last: "
        "another checkpoint; paper-visible: another success rule) and write this table minus it, "
        "episode by episode, with intervals: table1-<preset>-against-<PRESET>.md and .csv",
    )
    p.add_argument(
        "--verdicts-only",
        action="store_true",
        help="recompute the verdicts of the preset's written tables in --out (its ablation CSV, and "
        "the ablation check of its .md and .tex) from the intervals the ablation CSV holds, under the "
        "spec's rules and margin: nothing trained, evaluated or assembled",
    )
    p.add_argument(
        "--archive",
        type=Path,
        metavar="DIR",
        help="a folder of packed evaluations (tables/episodes/paper holds the paper presets'): each "
        "job's evaluation kept there is unpacked into the runs folder and counted, not run again, and "
        "each one it runs is packed there when it finishes (`kgnavbench episodes`)",
    )
    p.add_argument(
        "--train-only",
        action="store_true",
        help="train the preset's runs (all, or --job N's) and stop: no evaluation, "
        "no table; a later `table` evaluates and assembles",
    )
    p.add_argument(
        "--row",
        action="append",
        metavar="NAME",
        help="only this row of the preset, as named in the spec (repeatable): a partial table, written "
        "as table1-<preset>-partial.* (quick: table1-partial.*; the last one replaces an earlier one) "
        "and captioned with the rows it leaves out",
    )
    device_option(p)
    return p


def encoder_arguments(sub) -> argparse.ArgumentParser:
    """`kgnavbench encoder`'s arguments."""
    p = sub.add_parser(
        "encoder",
        help="retrain the frozen view encoder, or encode every state's view (cached)",
        description="pretrain: train the view encoder on the training kitchens' views (supervised: "
        "visible types, pitch, open receptacle) and write it; features: encode every state's view of "
        "the kitchens once, into the cache beside their state graphs.",
    )
    actions = p.add_subparsers(dest="action", required=True, parser_class=Parser)
    q = actions.add_parser("pretrain", help="train the view encoder on the training kitchens' views")
    q.add_argument("--epochs", type=positive, default=8)
    q.add_argument("--samples-per-epoch", type=positive, default=16_000)
    q.add_argument("--shift", type=int, default=4, help="random shift of the views in pixels (0: none)")
    seed_option(q, "the encoder's training")
    q.add_argument("--out", type=Path, help="where the weights go (default: the committed encoder file)")
    q = actions.add_parser("features", help="encode every state's view of the kitchens, cached")
    q.add_argument("kitchens", nargs="*", metavar="NAME", help="default: all 30")
    return p


# ------------------------------------------------------------------------------------------------
# One check per command: every inconsistency of its parsed options, reported at once (`verify`), so
# that the commands only run. What needs more than the options (a spec's presets and rows, a plugin's
# options) is checked where it is read.


def _writable(problems: list[str], check, path: Path, what: str) -> None:
    try:
        check(path, what)
    except UsageError as e:
        problems.append(str(e))


def _creatable_folder(problems: list[str], path: Path, what: str) -> None:
    """The folder can be made (or written, where it is): checked without making it, so that a command
    refused for another reason leaves nothing behind."""
    existing = next((p for p in (path, *path.parents) if p.exists()), None)
    if existing is None or not existing.is_dir():
        problems.append(f"{what} {str(path)!r}: cannot write there ({existing} is not a folder)")
    elif not os.access(existing, os.W_OK | os.X_OK):
        problems.append(f"{what} {str(path)!r}: cannot write there (no permission)")


def _recording(problems: list[str], args: argparse.Namespace) -> None:
    if args.record is not None:
        if not str(args.record).endswith(".rrd"):
            problems.append(f"--record {args.record}: a recording file must end in .rrd")
        else:
            _writable(problems, writable_file, args.record, "--record")


def eval_problems(args: argparse.Namespace) -> list[str]:
    problems: list[str] = []
    if args.checkpoint != "best" and not args.run:
        problems.append("--checkpoint chooses among a training run's checkpoints: give --run DIR too")
    _recording(problems, args)
    if args.video is not None:
        if args.video.suffix.lower() != ".mp4":
            problems.append(f"--video {args.video}: a video file must end in .mp4")
        else:
            _writable(problems, writable_file, args.video, "--video")
    _creatable_folder(problems, args.runs, "--runs")
    return problems


def train_problems(args: argparse.Namespace) -> list[str]:
    problems: list[str] = []
    if args.spec is not None and args.preset is None:
        problems.append("--spec names where --preset comes from: give --preset too")
    _recording(problems, args)
    _creatable_folder(problems, args.runs, "--runs")
    if args.seeds is not None and args.seed is not None:  # (--seed 0 too: its default is None here)
        problems.append("--seeds names every seed to train: not with --seed")
    if args.seeds is not None and len(args.seeds) > 1 and args.record is not None:
        problems.append("--record records one run's training curves: not with several --seeds")
    return problems


def figures_problems(args: argparse.Namespace) -> list[str]:
    if args.trained is not None and not args.trained.is_dir():
        return [f"--trained {args.trained}: no such folder"]
    return []


def table_problems(args: argparse.Namespace) -> list[str]:
    problems: list[str] = []
    if args.verdicts_only:
        flags = {
            "--jobs": args.jobs,
            "--job": args.job is not None,
            "--train-only": args.train_only,
            "--against": args.against is not None,
            "--row": bool(args.row),
            "--trained": args.trained is not None,
            "--archive": args.archive is not None,
            "--ray": bool(args.ray),
        }
        given = [flag for flag, on in flags.items() if on]
        if given:
            problems.append(
                f"--verdicts-only rewrites written tables and runs nothing: not with {', '.join(given)}"
            )
        return problems
    if args.ray and args.workers is not None:  # before connecting: the cluster's CPUs decide there
        problems.append(
            "--workers sets the jobs run at once on this machine; with --ray the cluster's CPUs do"
        )
    assembles = not args.jobs and args.job is None and not args.train_only
    if args.against is not None and not assembles:
        problems.append(
            "--against differences two assembled tables; --jobs, --job and --train-only assemble none"
        )
    if args.row and not assembles:
        problems.append(
            "--row picks the rows of a table to assemble; --jobs, --job and --train-only assemble none"
        )
    if args.archive is not None and args.train_only:
        problems.append("--archive keeps evaluations; --train-only runs none: one or the other")
    if args.archive is not None and not args.archive.is_dir():  # a typo would evaluate everything again
        problems.append(f"--archive {args.archive}: no such folder (create it to start an archive)")
    if args.trained is not None and not args.trained.is_dir():
        problems.append(f"--trained {args.trained}: no such folder")
    if args.trained is not None and args.train_only:
        problems.append("--trained takes runs already trained; --train-only trains them: one or the other")
    if args.ray_node_ip and not args.ray:
        problems.append("--ray-node-ip is this machine's address on a Ray cluster: give --ray too")
    return problems


def checkpoints_problems(args: argparse.Namespace) -> list[str]:
    problems: list[str] = []
    if not args.runs.is_dir():  # (a typo would read as "no run trained yet")
        problems.append(f"--runs {args.runs}: no such folder")
    if args.figure is not None:  # refused before hours of evaluation, not after the CSV is written
        import cv2

        if not cv2.haveImageWriter(str(args.figure)):
            problems.append(f"--figure {args.figure}: OpenCV writes no image of that extension (try .png)")
        else:
            _creatable_folder(problems, args.figure.parent, "--figure")
    if args.matched and (args.seed or args.unfinished):
        problems.append("--matched compares every finished seed of two rows: not with --seed or --unfinished")
    return problems


PROBLEMS = {
    "eval": eval_problems,
    "train": train_problems,
    "figures": figures_problems,
    "table": table_problems,
    "checkpoints": checkpoints_problems,
}


def verify(args: argparse.Namespace) -> None:
    """Every inconsistency of a command's options in one UsageError (one `kgnavbench: error:` line,
    the problems separated by '; '), before the command runs."""
    problems = PROBLEMS.get(args.command, lambda _args: [])(args)
    if problems:
        raise UsageError("; ".join(problems))
