"""The `kgnavbench` command line.

    kgnavbench kitchens [NAME] [--json]
    kgnavbench walk --kitchen NAME --actions A,B,...|random:N [--start x,z,heading,pitch]
                    [--size N] [--out DIR] [--json] [--seed S] [--placement-seed S]
    kgnavbench prepare [--kitchens A,B] [--workers N]
    kgnavbench targets NAME [--json]
    kgnavbench methods
    kgnavbench eval --method NAME [--success-rule visible|destination] [--stop-noop]
                    [--split table|train|val|test] [--kitchens A,B] [--episodes N] [--set KEY=VALUE]
                    [--seed S] [--runs DIR] [--run TRAIN_RUN [--checkpoint best|last]] [--json]
                    [--record FILE.rrd] [--record-episodes N] [--record-steps N] [--device auto|cpu|cuda]
    kgnavbench train --method NAME [--preset quick|paper [--spec FILE]] [--set KEY=VALUE] [--frames N]
                     [--seed S | --seeds S,S,...] [--kitchens A,B] [--runs DIR] [--record FILE.rrd]
                     [--device auto|cpu|cuda]
    kgnavbench table [--preset smoke|quick|paper] [--spec FILE] [--runs DIR] [--out DIR] [--workers N]
                     [--jobs | --job N | --ray ADDRESS] [--trained DIR | --train-only] [--row NAME ...]
                     [--device auto|cpu|cuda]
    kgnavbench ship RUN_DIR [--zoo DIR] [--last]
    kgnavbench checkpoints [--preset paper] [--runs DIR] [--row NAME] [--figure PNG] [--matched]
    kgnavbench figures [--preset quick] [--runs DIR] [--out DIR] [--trained DIR] [--row NAME ...]
                       [--curves-only]
    kgnavbench view FILE.rrd
    kgnavbench encoder pretrain [--epochs N] [--samples-per-epoch N] [--shift PX] [--seed S] [--out FILE]
    kgnavbench encoder features [NAME ...]

Bad input (an unknown kitchen or action, an unreachable start, a malformed pose, an out-of-range size,
an unusable output folder) prints one line ``kgnavbench: error: ...`` to stderr and exits with status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shlex
import signal
import sys
import threading
import time
from pathlib import Path

from . import arguments, plugins
from .arguments import UsageError
from .errors import KgnavbenchError
from .evaluate import SEEN_CAP, UNSEEN_CAP, EvalConfig, evaluate
from .graph import build_all, cache_dir
from .kitchens import KITCHEN_NAMES, check_name, kitchen_summary, load_kitchen
from .plugins import PluginError, load_plugin, parse_options, plugin_sources
from .tasks import SUCCESS_RULES, load_tasks
from .walk import walk
from .weights import selected_checkpoint

METHODS_IMPORT_TIMEOUT = 20.0  # seconds `methods` gives each plugin file to import
PROG = "kgnavbench"


def package_version() -> str:
    """The installed distribution's version (pyproject.toml's), with the git revision of a checkout."""
    from importlib.metadata import PackageNotFoundError, version

    from .files import git_revision

    try:
        number = version(PROG)
    except PackageNotFoundError:
        number = "unknown"
    revision = git_revision()
    return f"{number} ({revision})" if revision and revision != "unknown" else number


# ----------------------------------------------------------------------------------------------------
# kitchens


def _table(headers: list[str], rows: list[list], right: set[int]) -> str:
    cells = [headers] + [[str(v) for v in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = []
    for r in cells:
        parts = [r[i].rjust(widths[i]) if i in right else r[i].ljust(widths[i]) for i in range(len(r))]
        lines.append("  ".join(parts).rstrip())
    return "\n".join(lines)


def cmd_kitchens(args: argparse.Namespace) -> int:
    if args.name is None:
        rows = [kitchen_summary(load_kitchen(name)) for name in KITCHEN_NAMES]
        if args.json:
            print(json.dumps(rows, indent=1))
            return 0
        keys = ["name", "reachable_cells", "objects", "hidden_objects", "openable_receptacles"]
        headers = ["kitchen", "reachable cells", "objects", "hidden objects", "openable receptacles"]
        print(_table(headers, [[r[k] for k in keys] for r in rows], right={1, 2, 3, 4}))
        return 0
    k = load_kitchen(args.name)
    rows = [{"id": o.id, "type": o.type, "parent": o.parent, "hidden": o.hidden} for o in k.objects]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    table = [[r["id"], r["type"], r["parent"] or "-", "yes" if r["hidden"] else "no"] for r in rows]
    print(_table(["id", "type", "parent", "hidden"], table, right=set()))
    s = kitchen_summary(k)
    print(
        f"{k.name}: {s['objects']} objects, {s['hidden_objects']} hidden, "
        f"{s['openable_receptacles']} openable receptacles, {s['reachable_cells']} reachable cells"
    )
    return 0


# ----------------------------------------------------------------------------------------------------
# prepare, targets, methods, eval

# The paper's random-walk row of Table I, as printed there (arXiv 2005.02153): SR in %, the cells in
# the order of our tables
PAPER_RANDOM_WALK = (
    "static seen/seen 1.56, actionable seen/seen 0.23, static seen/unseen 14.86, "
    "static unseen kitchens 15.84, actionable unseen kitchens 3.25 (SR, %)"
)


def cmd_prepare(args: argparse.Namespace) -> int:
    kitchens = arguments.kitchen_list(args.kitchens)
    start = time.perf_counter()
    total = 0
    for kitchen, seconds, n in build_all(kitchens, workers=args.workers):
        total += n
        print(f"{kitchen:12s} {n:5d} states  {seconds:6.1f} s", flush=True)
    dt = time.perf_counter() - start
    print(f"{len(kitchens)} kitchens, {total} states ready in {cache_dir()} ({dt:.1f} s)")
    return 0


def cmd_targets(args: argparse.Namespace) -> int:
    tasks = load_tasks(check_name(args.name))
    rows = []
    for t in tasks.targets:
        dest = tasks.graph.pose(t.destination)
        opened = tasks.graph.opened[t.destination]
        rows.append(
            {
                "target": t.object_id,
                "kind": t.kind,
                "seen": t.seen,
                "destination": f"{dest.x:.2f},{dest.z:.2f},{dest.heading},{dest.pitch}",
                "opened": tasks.graph.world.objects[opened].id if opened >= 0 else None,
                "goal_states": len(t.goal_states),
                "episodes": len(t.starts),
            }
        )
    if args.json:
        print(json.dumps({"kitchen": tasks.kitchen, "split": tasks.split, "targets": rows}, indent=1))
        return 0
    n_seen = sum(r["seen"] for r in rows)
    if tasks.split == "train":
        who = f"{n_seen} seen (training) targets, {len(rows) - n_seen} unseen"
    else:
        who = (
            "every one unseen (Table I's unseen kitchens)" if tasks.split == "test" else "all for validation"
        )
    print(f"{tasks.kitchen} ({tasks.split} split): {len(rows)} targets, {who}")
    headers = ["target", "kind", "seen", "destination x,z,heading,pitch", "opened", "goal states", "episodes"]
    table = [
        [
            r["target"],
            r["kind"],
            "yes" if r["seen"] else "no",
            r["destination"],
            r["opened"] or "-",
            r["goal_states"],
            r["episodes"],
        ]
        for r in rows
    ]
    print(_table(headers, table, {5, 6}))
    return 0


def cmd_methods(args: argparse.Namespace) -> int:
    plugins.import_timeout = METHODS_IMPORT_TIMEOUT  # a plugin that blocks at import is listed, not waited on
    rows = []
    for name, source in plugin_sources().items():
        try:
            plugin = load_plugin(name)
            rows.append([name, plugin.description, source])
        except PluginError as e:
            rows.append([name, f"BROKEN: {e}", source])
    print(_table(["method", "description", "source"], rows, set()))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    plugins.step_timeout = args.step_timeout
    options = parse_options(args.set or [])
    load_plugin(args.method).config(options)  # unknown method or option: fail before any work
    config = EvalConfig(
        method=args.method,
        options=tuple(sorted(options.items())),
        success_rule=args.success_rule,
        stop_ends=not args.stop_noop and args.success_rule != "arrival",  # arrival: Stop is a no-op
        split=args.split,
        kitchens=tuple(arguments.kitchen_list(args.kitchens)) if args.kitchens is not None else (),
        episodes_per_target=args.episodes,
        seed=args.seed,
        run=str(args.run) if args.run else "",
        checkpoint=args.checkpoint,
        device=arguments.device_name(args.device),
    )
    progress = (lambda line: print(line, file=sys.stderr, flush=True)) if args.json else print
    arguments.writable_folder(args.runs, "--runs")
    # with --json, stdout is the JSON alone: whatever a plugin prints goes to stderr
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        run = evaluate(config, args.runs, progress=progress)
    if args.record is not None or args.video is not None:
        from .record import record_episodes  # rerun loads only when recording

        if args.record_steps is not None and args.record_steps > UNSEEN_CAP:
            progress(
                f"--record-steps {args.record_steps:,} is above the evaluation's caps ({SEEN_CAP} and "
                f"{UNSEEN_CAP} actions): each episode is recorded up to its cap"
            )

        done = record_episodes(
            args.method,
            options,
            args.record,
            kitchens=list(config.kitchens) or None,
            episodes=args.record_episodes,
            success_rule=config.success_rule,
            seed=config.seed,
            stop_ends=config.stop_ends,
            run=config.run or None,
            # the evaluated weights: the checkpoint --checkpoint chose
            checkpoint=(
                str(selected_checkpoint(config.run, config.method, config.checkpoint)) if config.run else None
            ),
            max_steps=args.record_steps,
            video=args.video,
        )
        where = " and ".join(str(p) for p in (args.record, args.video) if p is not None)
        progress(f"recorded {done['episodes']} episodes ({done['steps']} steps) to {where}")
    if args.json:
        summary = {f"{c}/{k}": vars(m) for (c, k), m in run.summary.items()}
        record = {"run": str(run.directory), "summary": summary}
        print(json.dumps(arguments.json_safe(record), indent=1, allow_nan=False))
        return 0
    print()
    print((run.directory / "table.md").read_text().rstrip())
    if args.method == "random_walk":
        print(f"paper, random walk (Table I, as printed): {PAPER_RANDOM_WALK}")
    steps = f", {run.steps:,} agent-steps ({run.steps / max(run.seconds, 1e-9):,.0f}/s)" if run.steps else ""
    n = len(run.resumed)
    resumed = f"; resumed {n} kitchen{'' if n == 1 else 's'} from disk" if n else ""
    print(f"{len(run.results)} episodes in {run.seconds:.1f} s{steps}{resumed}. Results: {run.directory}")
    return 0


# the success rules a training run takes: TrainOptions.check refuses "arrival" (an evaluation rule,
# Zhu et al.'s, whose Stop is a no-op), so a bad value is told these, not every rule evaluation takes
TRAINING_SUCCESS_RULES = tuple(rule for rule in SUCCESS_RULES if rule != "arrival")


def check_training_success_rule(method: str, options: dict) -> None:
    """A UsageError for a success_rule that is no rule at all (a typo), naming only the rules training
    takes; "arrival" is left to TrainOptions.check, whose message says it is an evaluation rule. Only for
    a plugin whose Config is a TrainOptions (another plugin's success_rule, or none, is its own)."""
    from .runs import TrainOptions

    rule = options.get("success_rule")
    if rule is None or rule in SUCCESS_RULES:
        return
    if issubclass(load_plugin(method).config_class, TrainOptions):
        raise UsageError(f"success_rule must be one of {TRAINING_SUCCESS_RULES} to train, not {rule!r}")


def cmd_train(args: argparse.Namespace) -> int:
    # torch and the trainer load only for the commands that need them
    from .runs import train_seeds

    options = parse_options(args.set or [])
    kitchens = arguments.kitchen_list(args.kitchens) if args.kitchens is not None else ()
    frames = args.frames if args.frames is not None else 10_000_000
    if args.preset is not None:  # Table I's protocol: the preset's options under --set's
        from .table_spec import SPEC_FILE, load_spec

        preset = load_spec(args.spec or SPEC_FILE).preset(args.preset)
        options = {**preset.options, **options}
        frames = args.frames if args.frames is not None else preset.frames
        kitchens = kitchens or preset.train_kitchens
    check_training_success_rule(args.method, options)
    arguments.writable_folder(args.runs, "--runs")
    # --seed's default is None (so that --seed 0 with --seeds is refused): no seed given is seed 0
    seeds = args.seeds or (args.seed if args.seed is not None else 0,)
    if args.preset is not None and len(seeds) > 1:  # --preset's runs are the table's for one seed only
        print(
            f"note: --seeds {','.join(map(str, seeds))} trains stacked runs of their own (config.json's "
            f"stacked_seeds), which `kgnavbench table --preset {args.preset}` does not reuse: it trains "
            "one run per seed (train those with --seed S)",
            flush=True,
        )
    directories = train_seeds(
        args.method,
        options,
        frames=frames,
        seeds=seeds,
        kitchens=kitchens,
        runs_dir=args.runs,
        progress=lambda line: print(line, flush=True),
        device=args.device,
    )
    if args.record is not None:
        from .record import record_training

        done = record_training(directories[0] / "metrics.csv", args.record)
        print(f"recorded {done['rows']} rows of training curves to {args.record}")
    from .distributed import from_env

    if from_env().main:  # (torchrun: one line, from rank 0)
        print("\n".join(map(str, directories)))  # the last lines: the run directories, for `eval --run`
    return 0


def cmd_figures(args: argparse.Namespace) -> int:
    from .figures import figures_of_table
    from .table_spec import SPEC_FILE, load_spec

    device = arguments.device_name(args.device)
    rows_named = tuple(args.row or ())
    spec = load_spec(args.spec or SPEC_FILE)
    preset = spec.preset(args.preset)
    if rows_named:
        from .jobs import only_rows

        only_rows(spec, preset, rows_named)
    if args.curves_only and args.trained is None:
        raise arguments.UsageError("--curves-only draws the runs of --trained DIR (zoo/): name it")
    # never over the whole preset's figures (the seeds' curves alone are their own file)
    out = args.out / "partial" if rows_named and not args.curves_only else args.out
    arguments.writable_folder(args.runs, "--runs")
    arguments.writable_folder(out, "--out")
    paths = figures_of_table(
        args.preset,
        args.runs,
        out,
        args.spec,
        print,
        trained=args.trained,
        device=device,
        rows_named=rows_named,
        curves_only=args.curves_only,
    )
    print(f"wrote {', '.join(str(p) for p in paths)}" if paths else "wrote nothing")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from .record import view

    return view(args.file)


def cmd_encoder(args: argparse.Namespace) -> int:
    # torch loads only for the commands that need it
    import torch

    from .encoder import ENCODER_FILE, pretrain_encoder, state_features

    if args.action == "pretrain":
        pretrain_encoder(
            epochs=args.epochs,
            seed=args.seed,
            out=args.out or ENCODER_FILE,
            samples_per_epoch=args.samples_per_epoch,
            shift=args.shift,
        )
        return 0
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    for kitchen in args.kitchens or KITCHEN_NAMES:
        start = time.perf_counter()
        n = len(state_features(check_name(kitchen)))
        seconds = time.perf_counter() - start
        print(f"{kitchen:12s} {n:6d} states  {seconds:5.1f} s  ({n / max(seconds, 1e-9):,.0f} states/s)")
    return 0


def cmd_table(args: argparse.Namespace) -> int:
    # torch and the trainer load only for the commands that need them
    from .jobs import Sources, job_commands, only_rows, preset_rows, run_job
    from .table import run_table
    from .table_files import to_markdown, write_table
    from .table_paired import to_paired_markdown, write_paired
    from .table_spec import SPEC_FILE, load_spec
    from .table_statistics import check_same_runs, paired_differences

    def say(line: str) -> None:
        print(line, flush=True)

    spec = load_spec(args.spec or SPEC_FILE)
    spec.preset(args.preset)  # an unknown preset is refused before anything runs
    if args.verdicts_only:
        from .reverdict import reverdict_tables

        arguments.writable_folder(args.out or spec.path.parent, "--out")
        print(reverdict_tables(spec, args.preset, args.out or spec.path.parent).summary())
        return 0
    args.workers = args.workers or os.cpu_count() or 1
    device = arguments.device_name(args.device)
    assembles = not args.jobs and args.job is None and not args.train_only
    common: tuple[str, ...] = ()  # --against: the rows both presets run
    if args.against is not None:
        check_same_runs(spec.preset(args.preset), spec.preset(args.against))  # before anything runs
        theirs = preset_rows(spec, spec.preset(args.against))
        ours = only_rows(spec, spec.preset(args.preset), tuple(args.row or ()))
        common = tuple(row.name for row in ours if row in theirs)
        if not common:
            raise UsageError(f"presets {args.preset!r} and {args.against!r} share no row to difference")
        for row in ours:
            if row not in theirs:
                print(f"--against: preset {args.against!r} has no row {row.name!r}: not differenced")
    sources = Sources(args.trained, args.train_only, args.archive)
    if args.jobs:  # each command carries --trained, --train-only and --archive
        print("\n".join(job_commands(spec, args.preset, args.runs, sources)))
        return 0
    arguments.writable_folder(args.runs, "--runs")
    if args.archive is not None and not os.access(args.archive, os.W_OK | os.X_OK):
        # a read-only checkout assembles from its archive: only an evaluation it lacks needs writing
        say(
            f"--archive {args.archive}: read-only; the evaluations it keeps are used, one it lacks runs "
            "in --runs and is not kept there"
        )
    if assembles:
        arguments.writable_folder(args.out or spec.path.parent, "--out")
    # how every table of this command runs its jobs
    on = {"progress": say, "workers": args.workers, "device": device, "sources": sources}
    if args.job is not None:
        run_job(spec, args.preset, args.job, args.runs, progress=say, device=device, sources=sources)
    if not assembles:
        if args.job is None:
            run_table(spec, args.preset, args.runs, **on, ray_address=args.ray, ray_node_ip=args.ray_node_ip)
        then = ["kgnavbench", "table", "--preset", args.preset, "--runs", str(args.runs)]
        for option, value in (
            ("--spec", args.spec), ("--trained", args.trained), ("--archive", args.archive),
            ("--out", args.out), ("--ray", args.ray), ("--ray-node-ip", args.ray_node_ip),
        ):  # fmt: skip
            then += [option, str(value)] if value else []
        print(f"then `{shlex.join(then)}` evaluates what is left and assembles the table")
        return 0
    ray = {"ray_address": args.ray, "ray_node_ip": args.ray_node_ip}
    result = run_table(spec, args.preset, args.runs, **on, rows_named=tuple(args.row or ()), **ray)
    paths = write_table(result, args.out or spec.path.parent)
    print()
    print(to_markdown(result).rstrip())
    if args.against is not None:
        base = run_table(spec, args.against, args.runs, **on, rows_named=common, **ray)
        differences = paired_differences(result, base)
        paths += write_paired(result, base, differences, args.out or spec.path.parent)
        print()
        print(to_paired_markdown(result, base, differences).rstrip())
    print(f"{paths.summary()}, in {result.seconds / 60:.1f} min")
    return 0


def cmd_ship(args: argparse.Namespace) -> int:
    from .jobs import write_zoo_listing
    from .table_spec import SPEC_FILE, load_spec
    from .zoo import same_job_runs, ship_run

    arguments.writable_folder(args.zoo, "--zoo")
    try:
        shipped = ship_run(args.run, args.zoo, ("best", "last") if args.last else ("best",))
    except OSError as e:
        raise UsageError(str(e)) from e  # an unwritable zoo folder
    size = sum(f.stat().st_size for f in shipped.folder.iterdir())
    total = sum(
        f.stat().st_size for f in args.zoo.rglob("*") if f.is_file() and not f.parent.name.startswith(".")
    )
    print(f"shipped {shipped.folder}: {size / 1e6:.1f} MB ({args.zoo} now {total / 1e6:.1f} MB)")
    if write_zoo_listing(args.zoo, load_spec(SPEC_FILE)):
        print(f"rewrote the listing in {args.zoo / 'README.md'}")
    else:
        print(
            f"{shipped.folder.name}: {shipped.method} seed {shipped.seed}, {shipped.frames:,} frames "
            f"(best.pt from {shipped.best_frames:,}); {args.zoo / 'README.md'} has no listing to rewrite"
        )
    for old in same_job_runs(args.zoo, shipped.folder):  # never removed here: saved data stays
        print(
            f"{old} trained the same job: `table --trained` takes the one this checkout's code trained, "
            f"or refuses both; remove the superseded one (git rm -r {old})"
        )
    return 0


def cmd_episodes(args: argparse.Namespace) -> int:
    from .archives import pack_evaluation, unpack_evaluation

    for path in args.pack or ():
        print(f"packed {path} into {pack_evaluation(path, args.out)}")
    for path in args.unpack or ():
        print(f"unpacked {path} into {unpack_evaluation(path, args.runs / 'eval')}")
    return 0


def cmd_checkpoints(args: argparse.Namespace) -> int:
    from .checkpoints import evidence, figure, matched, matched_figure, merge_matched_csv, preset_keep_every
    from .table_spec import SPEC_FILE, load_spec

    spec = load_spec(args.spec or SPEC_FILE)
    spec.preset(args.preset)
    device = arguments.device_name(args.device)
    csv_path = args.csv or spec.path.parent / f"checkpoints-{args.preset}.csv"
    arguments.writable_folder(csv_path.parent, "--csv")
    rows = tuple(args.row or ())
    lines = evidence(
        spec, args.preset, args.runs, csv_path, args.episodes, rows, device,
        lambda line: print(line, flush=True), tuple(args.seed or ()), args.unfinished,
    )  # fmt: skip
    if not csv_path.is_file():  # no finished run with snapshots: nothing was written, and none is claimed
        raise UsageError(
            f"no finished run of preset {args.preset!r} with snapshots in {args.runs}: "
            f"nothing written to {csv_path}"
        )
    print(f"wrote {csv_path}: {len(lines)} snapshots of {len({x['run'] for x in lines})} runs")
    if args.figure and lines:
        arguments.writable_folder(args.figure.parent, "--figure")
        order, keep_every = [row.name for row in spec.rows], preset_keep_every(spec, args.preset)
        print(f"wrote {figure(lines, args.figure, order, keep_every)}")
    if args.matched:
        pairs = matched(
            spec, args.preset, args.runs, args.episodes, rows, device, lambda line: print(line, flush=True)
        )
        matched_csv = csv_path.with_name(f"{csv_path.stem}-matched.csv")
        written = merge_matched_csv(matched_csv, pairs)
        print(f"wrote {matched_csv}: {len(pairs)} lines new, {len(written)} in all")
        if args.figure and pairs:
            print(f"wrote {matched_figure(pairs, args.figure.with_name(f'{args.figure.stem}-matched.png'))}")
    return 0


# ----------------------------------------------------------------------------------------------------
# parser and entry point


def build_parser() -> argparse.ArgumentParser:
    parser = arguments.Parser(
        prog=PROG, description="Target-driven visual navigation benchmark in the 30 iTHOR kitchens."
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=arguments.Parser)
    sub.required = True

    arguments.kitchens_arguments(sub).set_defaults(func=cmd_kitchens)
    arguments.walk_arguments(sub).set_defaults(func=walk)
    arguments.prepare_arguments(sub).set_defaults(func=cmd_prepare)
    arguments.targets_arguments(sub).set_defaults(func=cmd_targets)
    arguments.methods_arguments(sub).set_defaults(func=cmd_methods)
    arguments.eval_arguments(sub).set_defaults(func=cmd_eval)
    arguments.train_arguments(sub).set_defaults(func=cmd_train)
    arguments.figures_arguments(sub).set_defaults(func=cmd_figures)
    arguments.ship_arguments(sub).set_defaults(func=cmd_ship)
    arguments.checkpoints_arguments(sub).set_defaults(func=cmd_checkpoints)
    arguments.episodes_arguments(sub).set_defaults(func=cmd_episodes)
    arguments.view_arguments(sub).set_defaults(func=cmd_view)
    arguments.table_arguments(sub).set_defaults(func=cmd_table)
    arguments.encoder_arguments(sub).set_defaults(func=cmd_encoder)
    return parser


_NEGATIVE_VALUE = re.compile(r"-[0-9.]")


def _join_negative_values(argv: list[str]) -> list[str]:
    """argparse reads `--start -1.0,0.5,270,30` as two options; glue such a value to its option."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] == "--start" and i + 1 < len(argv) and _NEGATIVE_VALUE.match(argv[i + 1]):
            out.append(f"--start={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def _terminated(signum, frame):
    """SIGTERM (`kill`, a batch system's time limit) as Ctrl-C: what is half-written is removed (a
    recording's partial file, a staging folder) and saved results stay, instead of dying mid-write."""
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if in_main_thread else None
    try:
        return _main(argv)
    finally:
        if previous is not None:  # (None: a handler not set from Python, left as it is)
            signal.signal(signal.SIGTERM, previous)


# The checkout this package runs from: its default spec, tables/ and code are this folder's
PACKAGE_CHECKOUT = Path(__file__).resolve().parent.parent


def enclosing_checkout(folder: Path) -> Path | None:
    """The kgnavbench checkout (a folder with kgnavbench/__init__.py and tables/table1.toml) that holds
    `folder`, or None."""
    for candidate in (folder, *folder.parents):
        if (candidate / "kgnavbench" / "__init__.py").is_file() and (
            candidate / "tables" / "table1.toml"
        ).is_file():
            return candidate
    return None


def check_checkout(folder: Path) -> None:
    """Refuse to run from inside another checkout than the package's own (a worktree beside an editable
    install of the main checkout): its code, its default spec and its tables/ would be the other
    checkout's while zoo/ and runs/ are this folder's, so a table that differed would be written into
    the other checkout's committed files."""
    if enclosing_checkout(PACKAGE_CHECKOUT) != PACKAGE_CHECKOUT:
        return  # an installed package (site-packages), not a checkout's code: nothing to mix up
    here = enclosing_checkout(folder.resolve())
    if here is not None and here != PACKAGE_CHECKOUT:
        raise UsageError(
            f"this folder is in the checkout {here}, but the kgnavbench running is {PACKAGE_CHECKOUT}'s (its "
            f"code, default --spec and tables/ would be used); run `python -m kgnavbench ...` from {here}, "
            "which imports that checkout's code, or install it"
        )


def _main(argv: list[str]) -> int:
    try:
        args = build_parser().parse_args(_join_negative_values(argv))  # (--help answers anywhere)
        check_checkout(Path.cwd())
        # every path given is made absolute once, here: a plugin that changes the working directory
        # cannot split one command's files between two folders
        for name, value in vars(args).items():
            if isinstance(value, Path):
                setattr(args, name, value.absolute())
        arguments.verify(args)  # every inconsistency of the options at once; the command then only runs
        return args.func(args)
    except KgnavbenchError as e:  # every stage's: one line and exit status 2, never a traceback
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: saved results stay; the same command resumes
        print(f"{PROG}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except SystemExit as e:  # --help
        return e.code if isinstance(e.code, int) else 0
    except BrokenPipeError:  # `kgnavbench kitchens | head`: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:  # a view or map could not be written
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 1


__all__ = ["build_parser", "main"]
