"""Where a real training run's time goes: a row of a Table I preset trained as `kgnavbench train --preset`
trains it, for a few million frames, validation and checkpoints included, its wall time split by part.

    python benchmarks/train_profile.py              # +KG+Attention and +IL+TSE, 2.5M frames each
    python benchmarks/train_profile.py --rows "+KG+Attention" --frames 1000000
    python benchmarks/train_profile.py --beside     # with a second job on the other core

Each row runs `train.learn` (what the learned plugins' train hooks call) on the preset's options (one
thread under the paper preset), its training kitchens and seed 0, in a temporary run directory, with
`--frames` as the run's frames: the same run as `kgnavbench train --method M --preset paper --set
<row options> --frames N` (the start curriculum and IL's share scale with the frames, as they do
there). Timers wrap the package's
own functions and methods from outside (nothing is copied); each second of wall time goes to the
innermost part it is spent in, and validation and checkpoints keep everything under them:

- environment: the navigators' step and reset (`NavigationVectorEnv.step`, `.reset`);
- observation lookup: the network's inputs gathered from the feature and object tables (`Model.inputs`);
- acting forward: the network's forward passes, less their inputs (`Model.__call__`), while acting;
- acting, the rest: sampling, rewards, episode ends, numpy bookkeeping in `Actors.collect`;
- TSE bookkeeping: the sub-target sampler while acting (`SubtargetSampler.step`, `.finish`);
- knowledge graph: the per-update graph terms and the co-visibility counts (`Model.graph`, `CoVisibility.add`;
  their backward is in the update's backward);
- update forward: the losses' passes (`rollout_losses`, `expert_batch_loss`, `relabelled_windows`,
  `skill_extension_loss`);
- update backward (`Tensor.backward`) and the optimiser (gradient clipping and Adam's step);
- validation (`Trainer.validate`), checkpoints (`save_checkpoint`, `Trainer.state_dict`, `policy_state`);
- set-up: the trainer's state space, model and agents (`Trainer.__init__`), once per run;
- the rest: metrics rows, progress lines, the loop itself.

`--beside` starts a second copy of the same row (its output discarded) in another process first, so the
measured run shares the machine as a preset's two jobs side by side do. Nothing is written outside a
temporary folder.
"""

from __future__ import annotations

import argparse
import functools
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import torch

from kgnavbench import agent, losses, models, rollout, runs, train, vecenv
from kgnavbench.files import end_with_parent
from kgnavbench.plugins import load_plugin
from kgnavbench.table_spec import SPEC_FILE, load_spec

PARTS = (
    "set-up",
    "environment",
    "observation lookup",
    "acting forward",
    "acting, the rest",
    "TSE bookkeeping",
    "knowledge graph",
    "update forward",
    "update backward",
    "optimiser",
    "validation",
    "checkpoints",
    "the rest",
)
# parts that keep the time of everything they call (their forward passes are theirs, not acting's)
WHOLE = ("set-up", "validation", "checkpoints")


class Clock:
    """Exclusive wall time per part: a wrapped call's time, less that of the wrapped calls inside it."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.stack: list[list] = []  # [part, start, time of the wrapped calls inside]

    def wrap(self, part: str, function):
        @functools.wraps(function)
        def timed(*args, **kwargs):
            if self.stack and self.stack[-1][0] in WHOLE:
                return function(*args, **kwargs)
            frame = [part, time.perf_counter(), 0.0]
            self.stack.append(frame)
            try:
                return function(*args, **kwargs)
            finally:
                self.stack.pop()
                spent = time.perf_counter() - frame[1]
                self.seconds[part] += spent - frame[2]
                if self.stack:
                    self.stack[-1][2] += spent

        return timed

    def install(self) -> list:
        """Wrap the package's functions and methods in place; returns what `uninstall` puts back."""
        targets = [
            (train.Trainer, "__init__", "set-up"),
            (vecenv.NavigationVectorEnv, "step", "environment"),
            (vecenv.NavigationVectorEnv, "reset", "environment"),
            (agent.Model, "inputs", "observation lookup"),
            (agent.Model, "__call__", "acting forward"),
            (rollout.Actors, "collect", "acting, the rest"),
            (losses.SubtargetSampler, "step", "TSE bookkeeping"),
            (losses.SubtargetSampler, "finish", "TSE bookkeeping"),
            (agent.Model, "graph", "knowledge graph"),
            (models.CoVisibility, "add", "knowledge graph"),
            (train, "rollout_losses", "update forward"),
            (train, "expert_batch_loss", "update forward"),
            (train, "relabelled_windows", "update forward"),
            (train, "skill_extension_loss", "update forward"),
            (torch.Tensor, "backward", "update backward"),
            (torch.nn.utils, "clip_grad_norm_", "optimiser"),
            (torch.optim.Adam, "step", "optimiser"),
            (torch.optim.Adam, "zero_grad", "optimiser"),
            (train.Trainer, "validate", "validation"),
            (train, "save_checkpoint", "checkpoints"),
            (train.Trainer, "state_dict", "checkpoints"),
            (train.Trainer, "policy_state", "checkpoints"),
        ]
        saved = []
        for owner, name, part in targets:
            # a class's own attribute goes back as it was; an inherited one (Adam's zero_grad) is removed
            original = vars(owner).get(name, Clock) if isinstance(owner, type) else getattr(owner, name)
            saved.append((owner, name, original))
            setattr(owner, name, self.wrap(part, getattr(owner, name)))
        return saved

    @staticmethod
    def uninstall(saved: list) -> None:
        for owner, name, original in reversed(saved):
            if original is Clock:
                delattr(owner, name)
            else:
                setattr(owner, name, original)


def row_job(spec_path, preset_name: str, row_name: str):
    """(method, training options, frames, kitchens) of a row under a preset, as `table` trains it."""
    spec = load_spec(spec_path)
    preset = spec.preset(preset_name)
    rows = {r.name: r for r in spec.rows}
    if row_name not in rows:
        raise SystemExit(f"unknown row {row_name!r}; {spec.path} has {', '.join(rows)}")
    row = rows[row_name]
    return row.method, {**preset.options, **row.options}, preset.train_kitchens


def profile(method: str, options: dict, frames: int, kitchens, directory: Path) -> tuple[dict, float, int]:
    """Train the run for `frames` under the timers: (seconds per part, wall seconds, frames trained)."""
    plugin = load_plugin(method)
    config = plugin.config(options)
    run = runs.Run(directory, method, frames, 0, runs.training_kitchens(kitchens), lambda line: None, "cpu")
    model_config = plugin.module.model_config(config)
    clock = Clock()
    saved = clock.install()
    start = time.perf_counter()
    try:
        train.learn(run, config, model_config, rl=method != "imitation")
    finally:
        wall = time.perf_counter() - start
        Clock.uninstall(saved)
    done = train.read_metrics_rows(directory / "metrics.csv", frames * 2)
    trained = int(done[-1]["frames"]) if done else frames
    clock.seconds["the rest"] = wall - sum(clock.seconds.values())
    return dict(clock.seconds), wall, trained


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rows", default="+KG+Attention,+IL+TSE", help="rows of the spec, comma-separated")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--spec", default=str(SPEC_FILE))
    parser.add_argument("--frames", type=int, default=2_500_000, help="the run's frames (default 2.5M)")
    parser.add_argument("--beside", action="store_true", help="a second copy of the row runs meanwhile")
    parser.add_argument("--quiet-copy", action="store_true", help=argparse.SUPPRESS)  # the --beside copy
    args = parser.parse_args()
    if args.quiet_copy:  # ends with the measured process, killed or not, its temporary folder removed
        end_with_parent(os.getppid())
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    names = [r for r in args.rows.split(",") if r]
    print(
        f"preset {args.preset}, {args.frames:,} frames per row, seed 0, torch {torch.__version__}, "
        f"{'beside a second copy of the row' if args.beside else 'alone'}"
    )
    for name in names:
        method, options, kitchens = row_job(args.spec, args.preset, name)
        other = None
        if args.beside:
            command = [sys.executable, __file__, "--rows", name, "--preset", args.preset, "--spec", args.spec]
            command += ["--frames", str(args.frames * 2), "--quiet-copy"]  # outlasts the measured run
            other = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(20)  # past its start-up, into its training
            if other.poll() is not None:
                raise SystemExit(f"the second copy of {name} ended at once (exit {other.returncode})")
        try:
            with tempfile.TemporaryDirectory() as tmp:
                seconds, wall, trained = profile(method, options, args.frames, kitchens, Path(tmp))
        finally:
            if other is not None:
                beside_to_the_end = other.poll() is None
                other.terminate()
                other.wait()
        if other is not None and not beside_to_the_end:
            print(f"note: the second copy of {name} ended before the measured run did")
        if args.quiet_copy:
            continue
        training = wall - seconds.get("set-up", 0.0)
        print(
            f"\n{name} ({method}): {trained:,} frames in {wall:.1f} s, {trained / wall:,.0f} frames/s "
            f"({trained / training:,.0f} frames/s after the set-up)"
        )
        for part in PARTS:
            s = seconds.get(part, 0.0)
            print(f"  {part:20s} {s:8.1f} s  {100 * s / wall:5.1f}%")


if __name__ == "__main__":
    main()  # (one thread: `learn` sets the preset's `threads`)
