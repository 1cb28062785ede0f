"""Training and inference speed of the learned methods, end to end (navigators + learner), in frames/s.

    python benchmarks/train_speed.py                      # every row of Table I's learned methods
    python benchmarks/train_speed.py --updates 5 --kitchens FloorPlan1
    python benchmarks/train_speed.py --pixels --updates 3 --kitchens FloorPlan1   # end to end from views
    python benchmarks/train_speed.py --device cuda --agents 64                     # on a GPU
    python benchmarks/train_speed.py --preset paper --rows "+IL+TSE,+KG+Attention" --stacked 3
                       # Table I's rows as the paper preset trains them (its options, one thread), each
                       # alone, then 3 of its seeds stacked in this process (`train --seeds`)

For each method and options (default sizes: 64 agents in each of the 20 training kitchens, rollouts of
20 steps, LSTM 256, bf16 autocast) it builds the trainer exactly as `kgnavbench train` does, runs one
warm-up update, then times `--updates` updates: frames (agent steps) per second of the whole update
(the rollout's forward passes, the IL and TSE passes, backward and the optimiser step). Inference:
the trained-free network stepping the validation kitchens' fixed episodes under no_grad, as
validation and `eval --run` do. Nothing is written outside a temporary folder.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from kgnavbench import runs, train
from kgnavbench.device import resolve
from kgnavbench.plugins import load_plugin
from kgnavbench.table_spec import load_spec

ROWS = [
    ("ff_a3c", {}),
    ("lstm_a3c", {}),
    ("lstm_a3c", {"il": "true"}),
    ("lstm_a3c", {"tse": "true"}),
    ("lstm_a3c", {"il": "true", "tse": "true"}),
    ("kg_attention", {"attention": "false"}),
    ("kg_attention", {"il": "false", "tse": "false"}),
    ("kg_attention", {}),
]


def trainer_of(method: str, options: dict, kitchens: tuple[str, ...], directory: Path, device: str, seed=0):
    plugin = load_plugin(method)
    config = plugin.config(options)
    run = runs.Run(directory, method, 10**12, seed, kitchens, progress=lambda line: None, device=device)
    model_config = plugin.module.model_config(config)
    return train.Trainer(run, config, model_config, rl=method != "imitation"), config


def synchronize(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--updates", type=int, default=10)
    parser.add_argument("--kitchens", default="", help="training kitchens (default: all 20)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--agents", type=int, default=0, help="agents per training kitchen (default: the option's default)"
    )
    parser.add_argument("--methods", default="", help="only these methods, e.g. kg_attention,lstm_a3c")
    parser.add_argument(
        "--set", action="append", default=[], metavar="K=V", help="a training option for every row"
    )
    parser.add_argument(
        "--pixels", action="store_true", help="only lstm_a3c end to end from the views (pixels=true)"
    )
    parser.add_argument("--device", default="cpu", help="auto | cpu | cuda (default cpu)")
    parser.add_argument(
        "--stacked",
        type=int,
        default=0,
        metavar="S",
        help="after each row alone, S of its seeds stacked in one process (`train --seeds`): their "
        "summed frames/s, and its ratio to one seed's",
    )
    parser.add_argument(
        "--preset",
        help="Table I's rows (--rows) under this preset of tables/table1.toml: its options and threads",
    )
    parser.add_argument("--rows", default="", help="with --preset: these rows, by name (comma-separated)")
    args = parser.parse_args()
    device = str(resolve(args.device))
    rows = [("lstm_a3c", {"pixels": "true"})] if args.pixels else ROWS
    if args.preset:
        preset = load_spec().preset(args.preset)
        named = {r.name: r for r in load_spec().rows}
        wanted = [name.strip() for name in args.rows.split(",") if name.strip()] or list(preset.rows)
        unknown = [name for name in wanted if name not in named]
        if unknown:
            parser.error(f"unknown rows {unknown}; the spec has {', '.join(named)}")
        rows = [(named[name].method, {**preset.options, **named[name].options}) for name in wanted]
        args.threads = preset.threads or args.threads
    if args.methods:
        rows = [(m, o) for m, o in rows if m in args.methods.split(",")]
    extra = dict(kv.split("=", 1) for kv in args.set)
    if args.agents:
        extra["agents_per_kitchen"] = str(args.agents)
        if args.agents < 7 and "fixed_targets" in runs.TrainOptions.__dataclass_fields__:
            extra.setdefault("fixed_targets", "false")  # one target per agent needs 7 agents per kitchen
    rows = [(m, {**o, **extra}) for m, o in rows]
    torch.set_num_threads(args.threads)
    kitchens = runs.training_kitchens(tuple(k for k in args.kitchens.split(",") if k))
    print(f"{len(kitchens)} training kitchens, {args.threads} threads, {device}, torch {torch.__version__}")
    with tempfile.TemporaryDirectory() as tmp:
        for method, options in rows:
            trainer, config = trainer_of(method, options, kitchens, Path(tmp), device)
            trainer.update()  # warm-up: first-call allocations
            synchronize(device)
            start, frames = time.perf_counter(), trainer.frames
            for _ in range(args.updates):
                trainer.update()
            synchronize(device)
            seconds = time.perf_counter() - start
            rate = (trainer.frames - frames) / seconds
            shown = {k: v for k, v in options.items() if k not in ("agents_per_kitchen", "fixed_targets")}
            label = method + (" " + " ".join(f"{k}={v}" for k, v in shown.items()) if shown else "")
            print(
                f"train  {label:44s} {trainer.total_agents:5d} agents  {rate:9,.0f} frames/s  "
                f"({args.updates} updates in {seconds:.1f} s; il={config.il} tse={config.tse})"
            )
            if args.stacked > 1:
                seeds = [
                    trainer_of(method, options, kitchens, Path(tmp) / str(s), device, s)[0]
                    for s in range(args.stacked)
                ]
                train.stacked_update(seeds)  # warm-up
                synchronize(device)
                start, frames = time.perf_counter(), sum(t.frames for t in seeds)
                for _ in range(args.updates):
                    train.stacked_update(seeds)
                synchronize(device)
                seconds = time.perf_counter() - start
                summed = (sum(t.frames for t in seeds) - frames) / seconds
                print(
                    f"train  {label + f' x{args.stacked} stacked':44s} {trainer.total_agents:5d} agents  "
                    f"{summed:9,.0f} frames/s summed over the seeds, {summed / rate:.2f}x one seed "
                    f"({args.updates} updates in {seconds:.1f} s)"
                )
        if args.pixels:
            return
        # inference: validation episodes (cap 1000) with the last trainer's network, as `eval --run` does
        trainer.opts.val_episodes = 1
        trainer.validate()  # loads the validation kitchens
        trainer.opts.val_episodes = 20
        start = time.perf_counter()
        sr, spl, frames, _ = trainer.validate()
        seconds = time.perf_counter() - start
        print(
            f"infer  {'kg_attention (validation episodes)':44s} {frames:,} frames in {seconds:.1f} s: "
            f"{frames / seconds:9,.0f} frames/s"
        )


if __name__ == "__main__":
    main()
