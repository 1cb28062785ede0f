"""Stage 18 — train: the learned methods' trainer. A synchronous batched A2C with the paper's A3C losses,
imitation learning (IL), target skill extension (TSE), checkpoints, logs and resumption.

It stands on the stages before it: the run directory, options and checkpoints (kgnavbench/runs.py),
the network with its inputs around it (kgnavbench/agent.py), the acting half of the algorithm
(kgnavbench/rollout.py: the agents in the batched navigators of kgnavbench/vecenv.py, stepped n times
per update), the learning half (kgnavbench/learning.py: the losses of an update, as plain functions)
and a row's seeds stacked into one network (kgnavbench/stacking.py). Read it top to bottom:

1. `Trainer`: `update` is the algorithm, one rollout (`collect`: 20 steps of all agents) and one
   gradient step on its losses (`loss`, `step`); validation on fixed episodes; and the checkpoint
   (model, optimiser, every RNG, every agent's episode and LSTM state, the co-visibility counts): a
   run killed at any moment resumes from `last.pt` exactly as if it had never stopped. Under torchrun
   each rank holds its share of the agents (kgnavbench/distributed.py). `stacked_update`: the same
   update of S seeds of one row at once.
2. `learn`: the loop over one run (or S stacked ones), `metrics.csv`, progress lines, `last.pt`,
   `best.pt` (Table I's checkpoint rule, the paper's words: the checkpoint with the highest validation
   SR, ties to the later) and, with keep_every, weight snapshots.
A trained checkpoint becomes a plugin policy in the next stage, kgnavbench/policy.py.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import random
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from . import distributed, encoder, models, stacking
from .agent import Model, run_episodes
from .files import atomic_write, duration_text
from .intervals import standard_error
from .kitchens import KITCHEN_NAMES
from .learning import expert_batch_loss, relabelled_windows, rollout_losses, skill_extension_loss
from .losses import Sequences, assign_targets, expert_sequences
from .rollout import Actors, Rollout
from .runs import (
    CHECKPOINT_FORMAT,
    POLICY_KEYS,
    Run,
    TrainError,
    TrainOptions,
    checkpoint_differences,
    load_checkpoint,
    read_metrics_rows,
    save_checkpoint,
    seconds_at,
)
from .tasks import load_task_file
from .vecenv import StateSpace, build_space, curriculum_reach

VALIDATION_CAP = 1000  # validation kitchens are unseen kitchens: evaluate's cap of 1000 actions
# FF A3C is validated where its scene-specific heads exist: its own training kitchens' seen targets,
# evaluate's cap for them, from start states drawn with this seed offset, never a fixed episode's start
SEEN_VALIDATION_CAP = 100
# how best.pt was chosen, in finished.json: runs finished before it was written (no "best_rule") kept
# the latest checkpoint within one standard error of the best so far (`within_one_standard_error`)
BEST_RULE = "highest validation SR, ties to the later"
FF_VALIDATION_SEED = 0xFFA3C
ESTIMATE_AFTER = 20.0  # seconds of training before the run says how long the rest will take
METRICS = (
    "frames",
    "seconds",  # training time of the whole run, the sessions before a resume included
    "frames_per_s",  # this session's rate
    "updates",
    "episodes",
    "mean_reward",
    "mean_return",
    # training episodes (curriculum starts, training's cap, sampled actions): the SR of each target
    # over its episodes that ended since the last row, averaged over the targets, so that every target
    # weighs alike, as in evaluation. Per episode (episode_success_rate) a target whose agents fail
    # fast, Stopping early, ends many more episodes and drags it down (measured, FloorPlan1: 13.8% per
    # episode, 35.7% per target, where the fixed episodes scored 34%)
    "success_rate",
    "episode_success_rate",
    "rl_loss",
    "il_loss",
    "tse_loss",
    "val_sr",
    "val_spl",
    "val_episodes",  # what the validation SR was measured on: its standard error is sqrt(p (1 - p) / n)
)


# ------------------------------------------------------------------------------------------------
# 1. The trainer: the agents act (kgnavbench/rollout.py), then one gradient step on what they did


class Trainer:
    """A2C over all training kitchens at once, with optional IL and TSE; its whole state checkpoints.

    `update` is the algorithm, in its two halves: `collect` (the agents act n steps under the current
    weights, without autograd) and one gradient step on the sum of the rollout's A2C loss
    (`rollout_losses`), IL's (`expert_batch_loss`, or DAgger's labels on the rollout's own states) and
    TSE's (`relabelled_windows`, `skill_extension_loss`), plain functions of kgnavbench/learning.py.
    `learn` drives trainers (one per run, several for stacked seeds) to their frames; `after_update`
    logs, validates and checkpoints after each update."""

    def __init__(
        self,
        run: Run,
        options: TrainOptions,
        model_config: models.ModelConfig,
        rl: bool,
        ranks: distributed.Ranks = distributed.SINGLE,
    ):
        """A trainer at frame 0 (`learn` loads a checkpoint into it to resume).

        :param run: the run directory and what names it (method, kitchens, frames, seed, device)
        :param options: the training options (`runs.TrainOptions`, resolved)
        :param model_config: the plugin's network; its scene count is set to the run's kitchens
        :param rl: whether the method learns from reward (False: IL alone, `imitation`)
        :param ranks: this process's rank among torchrun's (default: a single process)
        """
        self.run, self.opts, self.rl, self.ranks = run, options, rl, ranks
        self.kitchens = list(run.kitchens)
        self.model_config = dataclasses.replace(model_config, n_scenes=len(self.kitchens))
        self.ff = self.model_config.arch == "ff"
        self.space = build_space(
            self.kitchens, "seen", options.success_rule, self.model_config.pixels, options.tse_unseen_targets
        )
        self.device = torch.device(run.device)
        self.model = self._build_model()
        self.optimizer = torch.optim.Adam(self.model.net.parameters(), lr=options.lr)
        # every rank starts from the same weights (above); its agents draw from generators of their own
        # (rank 0's are a single process's)
        seed = run.seed if ranks.rank == 0 else run.seed + 1_000_003 * ranks.rank
        # the actions' sampler; IL's expert batches draw from it too
        self.generator = torch.Generator(self.device).manual_seed(seed)
        # training draws nothing from Python's `random`, but a checkpoint saves its state: seeded, two
        # identical runs write identical checkpoints (and a plugin that uses it stays reproducible)
        random.seed(seed)
        self.frames = self.updates = 0
        self.best_val_sr = -1.0  # the validation SR of the selected checkpoint (best.pt)
        self.val_max = -1.0  # the best validation SR so far
        self.stats = self._empty_stats()
        # per target row: episodes ended and successes since the last metrics row
        self.target_stats = np.zeros((2, len(self.space.target_ids)), np.float64)
        self.val_space: StateSpace | None = None
        self.total_agents = options.agents_per_kitchen * len(self.kitchens)
        self.actors, assigned = self._build_actors(seed)
        self.il = options.il or not rl
        self.dagger = self.il and options.il_expert == "dagger"
        self.experts = self._expert_sequences(assigned) if self.il and not self.dagger else None

    def _build_model(self) -> Model:
        """The network at its initial weights (seeded by the run's seed), on the run's device."""
        # seeded after build_space: encoding features on a cache miss draws from torch's generator
        torch.manual_seed(self.run.seed)
        net = models.make_model(self.model_config)
        if net.encoder is not None:  # end to end: start from the committed encoder and its statistics
            net.encoder.load_state_dict(encoder.load_encoder().state_dict())
            stats = encoder.encoder_feature_stats()
            net.feature_mean.copy_(stats["mean"])
            net.feature_std.copy_(stats["std"])
        net.to(self.device)
        return Model(net, self.model_config, models.CoVisibility(), self.opts.bf16, self.device)

    def _build_actors(self, seed: int) -> tuple[Actors, np.ndarray | None]:
        """This rank's share of the training agents (`agents_per_kitchen` in every kitchen), and every
        agent's assigned target row (None: a new target every episode)."""
        options, ranks = self.opts, self.ranks
        kitchen = np.repeat(np.arange(len(self.kitchens)), options.agents_per_kitchen)
        assigned = None
        if options.fixed_targets:
            assigned = assign_targets(self.space, kitchen, options.targets_per_kitchen)
        mine = np.arange(self.total_agents)[ranks.rank :: ranks.world]  # this rank's share of the agents
        if not len(mine):
            raise TrainError(f"{self.total_agents} agents cannot be shared by {ranks.world} ranks")
        actors = Actors(
            self.space,
            kitchen[mine],
            None if assigned is None else assigned[mine],
            options,
            self.model,
            self.generator,
            seed,
            self.reach(),
        )
        return actors, assigned

    def _expert_sequences(self, assigned: np.ndarray | None) -> Sequences:
        """IL's expert sequences (`il_expert`), drawn from their own generator; only the trained
        targets' where each kitchen trains a few (`targets_per_kitchen`)."""
        options = self.opts
        rng = np.random.default_rng([self.run.seed, 1])
        experts = expert_sequences(self.space, options.il_expert, options.il_walk, rng)
        if options.targets_per_kitchen:
            kept = np.unique(assigned)
            experts = Sequences(
                experts.states[kept], experts.actions[kept], experts.mask[kept], experts.goal[kept]
            )
        return experts

    @staticmethod
    def _empty_stats() -> dict:
        keys = (
            "frames", "reward", "episodes", "successes", "returns", "rl", "il", "tse",
            "losses_rl", "losses_il", "losses_tse",
        )  # fmt: skip
        return dict.fromkeys(keys, 0.0)

    def reach(self) -> int | None:
        """The curriculum's farthest start (actions from the destination) at this frame; None: off or over."""
        return curriculum_reach(self.frames, self.opts.start_curriculum * self.run.frames)

    # -- one update ------------------------------------------------------------------------------
    def update(self) -> None:
        """One rollout of every agent (or, IL only, one expert batch) and one gradient step."""
        graph, imitate = self.model.graph(), self.imitating()
        rollout = self.collect(graph) if self.rl or self.dagger else None
        self.step(self.loss(graph, imitate, rollout))

    def imitating(self) -> bool:
        """Whether this update (its frames before the rollout) mixes in IL."""
        return self.il and (not self.rl or self.frames < self.opts.il_fraction * self.run.frames)

    def loss(self, graph, imitate: bool, rollout: Rollout | None, replayed=None) -> torch.Tensor:
        """The update's loss: the rollout's A2C loss (and DAgger's), IL's expert batch, TSE's relabelled
        windows, as the options say; their values go to the metrics. `replayed`: the rollout's logits
        and values with autograd where a stacked pass computed them (kgnavbench/stacking.py); None:
        `Model.unroll` replays it here."""
        opts = self.opts
        loss = torch.zeros((), device=self.device)

        def add(name: str, term: torch.Tensor, weight: float = 1.0) -> None:
            nonlocal loss
            loss = loss + (term if weight == 1.0 else weight * term)
            self.stats[name] += term.item()
            self.stats[f"losses_{name}"] += 1

        windows: list = []  # TSE: the sub-target windows of the episodes that end in this rollout
        if rollout is not None:
            rl_loss, dagger_loss = rollout_losses(
                self.model, self.space, rollout, graph, opts, imitate and self.dagger, replayed
            )
            windows = rollout.windows
            if self.rl:
                add("rl", rl_loss)
            if dagger_loss is not None:
                add("il", dagger_loss, opts.il_weight)
        if imitate and not self.dagger:
            il_loss, n_frames = expert_batch_loss(
                self.model, self.space, self.experts, opts.il_batch, self.generator, graph
            )
            add("il", il_loss, opts.il_weight)
            if not self.rl:
                self.stats["frames"] += n_frames  # this rank's (metrics sum the ranks')
                self.frames += int(distributed.sum_tensor(torch.tensor(n_frames), self.ranks))
        if self.rl and opts.tse:
            relabelled = relabelled_windows(windows, opts, self.actors.rng)
            if relabelled is not None:
                add(
                    "tse",
                    skill_extension_loss(self.model, self.space, relabelled, graph, opts),
                    opts.tse_weight,
                )
        return loss

    def step(self, loss: torch.Tensor | None) -> None:
        """The gradient step: backward from `loss` (None: a stacked loss's backward has filled the
        gradients already), the ranks' gradients averaged, clipped, Adam."""
        if loss is not None:
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
        distributed.average_gradients(self.model.net.parameters(), self.ranks)
        torch.nn.utils.clip_grad_norm_(self.model.net.parameters(), self.opts.max_grad_norm)
        self.optimizer.step()
        self.updates += 1
        distributed.check_replicas(self.model.net.parameters(), self.ranks, self.updates)

    def collect(self, graph) -> Rollout:
        """The acting half: n steps of every agent (`Actors.collect`), then `collected`."""
        acting = self.acting()
        return self.collected(self.actors.collect(self.model, graph, *acting))

    def acting(self) -> tuple[int | None, dict, np.ndarray]:
        """Before a rollout: Stop ends training episodes from stop_ends_from on. What `Actors.collect`
        takes besides the model: the curriculum's reach and where the episodes' numbers go."""
        opts = self.opts
        self.actors.envs.stop_ends = opts.stop_ends_from is not None and self.frames >= opts.stop_ends_from
        return self.reach(), self.stats, self.target_stats

    def collected(self, rollout: Rollout) -> Rollout:
        """After a rollout: the knowledge graph's co-visibility counts add the views it reached, every
        rank's on every rank; the frames are counted."""
        n, b = rollout.states.shape
        if self.model.uses_graph:
            covis, seen = self.model.covis, self.space.objects[rollout.reached.reshape(-1)]
            if self.ranks.world == 1:
                covis.add(seen)
            else:
                before = covis.counts.clone()
                covis.add(seen)
                covis.counts = before + distributed.sum_tensor(covis.counts - before, self.ranks)
        self.frames += n * self.total_agents  # every rank's agents stepped n times
        self.stats["frames"] += n * b  # this rank's (metrics sum the ranks')
        return rollout

    # -- validation ------------------------------------------------------------------------------
    def validate(self) -> tuple[float, float, int, int]:
        """SR and SPL (percent) on the validation kitchens' fixed episodes (the first val_episodes per
        target), cap 1000, under the success rule, the frames and the episodes it took; its own seeded
        sampling, so training is untouched. FF A3C: `ff_validation_episodes`, in its own kitchens."""
        if self.ff:
            targets, starts = ff_validation_episodes(self.space, self.validation_count(), self.run.seed)
            scene = self.space.target_kitchen[targets]
            sr, spl, frames = run_episodes(
                self.model, self.space, targets, starts, SEEN_VALIDATION_CAP, self.run.seed, scene
            )
            return sr, spl, frames, len(targets)
        sp = self.validation_space()
        rows = [(r, s) for r, starts in enumerate(sp.fixed_starts) for s in starts[: self.opts.val_episodes]]
        targets = np.array([r for r, _ in rows], np.int64)
        starts = np.array([s for _, s in rows], np.int64)
        sr, spl, frames = run_episodes(self.model, sp, targets, starts, VALIDATION_CAP, self.run.seed)
        return sr, spl, frames, len(rows)

    def validation_space(self) -> StateSpace:
        """The first val_kitchens validation kitchens, all their targets; built on first use."""
        if self.val_space is None:
            names = load_task_file()["splits"]["val"][: self.opts.val_kitchens]
            self.val_space = build_space(
                sorted(names, key=KITCHEN_NAMES.index),
                "all",
                self.opts.success_rule,
                self.model_config.pixels,
            )
        return self.val_space

    def validation_count(self) -> int:
        """How many episodes the other rows validate on: val_episodes per target of the val kitchens."""
        return sum(min(len(s), self.opts.val_episodes) for s in self.validation_space().fixed_starts)

    # -- checkpoints -----------------------------------------------------------------------------
    def state_dict(self, weights: bool = True) -> dict:
        return {
            "format": CHECKPOINT_FORMAT,
            "method": self.run.method,
            "options": asdict(self.opts),
            "model_config": asdict(self.model_config),
            "kitchens": self.kitchens,
            "seed": self.run.seed,
            "frames": self.frames,
            "updates": self.updates,
            "tick": self.actors.tick,
            "best_val_sr": float(self.best_val_sr),
            "val_max": float(self.val_max),
            "stats": {k: float(v) for k, v in self.stats.items()},
            "target_stats": torch.from_numpy(self.target_stats.copy()),
            "model": self.model.net.state_dict() if weights else None,
            "optimizer": self.optimizer.state_dict() if weights else None,
            "covis": self.model.covis.state_dict(),
            "rng": {
                "numpy": json.dumps(self.actors.rng.bit_generator.state),  # plain data: weights_only loads it
                "sampling": self.generator.get_state(),
                "torch": torch.get_rng_state(),
                "python": random.getstate(),
            },
            **self.actors.state_dict(),  # agents, hidden, history, tse
        }

    def policy_state(self) -> dict:
        """What a policy needs of the checkpoint (`policy.load_policy`): the weights, their config and
        the knowledge graph's counts; no optimiser, generators or agents (a snapshot, not a resume point)."""
        state = {**self.state_dict(weights=False), "model": self.model.net.state_dict()}
        return {k: state[k] for k in POLICY_KEYS}

    RANK_STATE = ("rng", "agents", "hidden", "history", "tse")  # what differs between the ranks

    def rank_state(self) -> dict:
        """This rank's part of the checkpoint: its agents, their LSTM states and its generators."""
        return {k: v for k, v in self.state_dict(weights=False).items() if k in self.RANK_STATE}

    def load_state_dict(self, ck: dict) -> None:
        if self.ranks.world > 1:  # this rank's own agents and generators
            ranks = ck.get("ranks")
            if not isinstance(ranks, list) or len(ranks) != self.ranks.world:
                raise ValueError(f"the checkpoint holds no state for {self.ranks.world} ranks")
            ck = {**ck, **ranks[self.ranks.rank]}
        self.model.net.load_state_dict(ck["model"])
        self.optimizer.load_state_dict(ck["optimizer"])
        self.model.covis.load_state_dict(ck["covis"])
        self.actors.rng.bit_generator.state = json.loads(ck["rng"]["numpy"])
        self.generator.set_state(ck["rng"]["sampling"])
        torch.set_rng_state(ck["rng"]["torch"])
        random.setstate(ck["rng"]["python"])
        self.actors.load_state_dict(ck, self.device)
        self.frames, self.updates, self.actors.tick = ck["frames"], ck["updates"], ck["tick"]
        self.best_val_sr, self.stats = ck["best_val_sr"], dict(ck["stats"])
        self.val_max = ck.get("val_max", self.best_val_sr)
        if "target_stats" in ck:
            self.target_stats = ck["target_stats"].numpy().copy()


def stacked_update(trainers: list[Trainer]) -> None:
    """`Trainer.update` of S seeds of one row at once (kgnavbench/stacking.py): their rollouts in
    lock-step and their learning passes stacked, then each seed's own losses, gradient clipping and
    Adam step. The seeds' losses are summed for one backward pass; each seed's parameters get the
    gradient of its own loss only."""
    models = [t.model for t in trainers]
    graphs = [m.graph() for m in models]
    imitate = [t.imitating() for t in trainers]
    weights, readout = stacking.stacked_weights(models), stacking.stacked_readout(graphs)
    replayed = [None] * len(trainers)
    rollouts = [None] * len(trainers)
    if trainers[0].rl or trainers[0].dagger:
        acting = [t.acting() for t in trainers]
        actors = [t.actors for t in trainers]
        collected = stacking.collect(actors, models, graphs, *stacking.for_acting(weights, readout), acting)
        rollouts = [t.collected(r) for t, r in zip(trainers, collected)]
        replayed = stacking.unroll(models, [t.space for t in trainers], rollouts, weights, readout)
    losses = [t.loss(*args) for t, *args in zip(trainers, graphs, imitate, rollouts, replayed)]
    for t in trainers:
        t.optimizer.zero_grad(set_to_none=True)
    torch.stack(losses).sum().backward()
    for t in trainers:
        t.step(None)


def ff_validation_episodes(space: StateSpace, at_least: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """FF A3C's validation episodes (Zhu et al. had no validation rooms, and its heads exist for its
    training kitchens only): the seen targets of its training kitchens that have a training start
    besides their fixed evaluation episodes' (a small kitchen's target can have none: 7 of the
    paper preset's 140, six in FloorPlan25 and one in FloorPlan29), as many episodes each as make
    at least `at_least` in all (the other rows' validation count), from those starts, drawn with
    the run's own seed. The same every time."""
    pools = []
    for r in range(len(space.target_ids)):
        pool = space.start_flat[space.start_ptr[r] : space.start_ptr[r + 1]]
        pools.append(pool[~np.isin(pool, space.fixed_starts[r])])
    kept = [r for r, pool in enumerate(pools) if len(pool)]
    if not kept:
        raise TrainError("no training target has a training start outside the fixed episodes")
    per_target = -(-at_least // len(kept))
    rng = np.random.default_rng([FF_VALIDATION_SEED, seed])
    targets, starts = [], []
    for r in kept:
        starts.append(rng.choice(pools[r], per_target, replace=len(pools[r]) < per_target))
        targets.append(np.full(per_target, r, np.int64))
    return np.concatenate(targets), np.concatenate(starts).astype(np.int64)


# ------------------------------------------------------------------------------------------------
# 2. The loop: logs, checkpoints, resumption


def _csv_text(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, METRICS)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


@dataclasses.dataclass
class Session:
    """One run's bookkeeping around its trainer in `learn`'s loop: where it logs, validates and keeps
    checkpoints next, and the clock."""

    run: Run
    trainer: Trainer
    progress: Callable[[str], None]
    seconds_before: float  # the training time of the sessions before a resume
    next_log: int
    next_val: int
    next_keep: int | None
    t0: float = dataclasses.field(default_factory=time.perf_counter)
    f0: int = 0  # the frames it resumed at
    estimated: bool = False  # long work says how long: once, after the first ESTIMATE_AFTER seconds

    @property
    def done(self) -> bool:
        return self.trainer.frames >= self.run.frames


def learn(run: Run, options: TrainOptions, model_config: models.ModelConfig, rl: bool = True) -> Path:
    """Train (or resume) a run: A2C (rl=True) with IL and TSE as the options say, or IL alone. With
    `run.stacked` (`kgnavbench train --seeds`), those runs too, in this process: one update of every
    seed at once (`stacked_update`) while they are at the same frames, alone one by one where a resume
    left one behind.

    :param run: the run directory and what names it (`runs.Run`: method, kitchens, frames, seed, device)
    :param options: the training options, checked here (`runs.TrainOptions`)
    :param model_config: the plugin's network
    :param rl: False for IL alone (the `imitation` plugin)
    :return: the run directory, holding best.pt, last.pt, metrics.csv and finished.json (of stacked
        seeds, the first seed's; the others' are `run.stacked`'s)
    """
    options.check()
    torch.set_num_threads(options.threads)
    ranks = distributed.start(torch.device(run.device))
    if run.stacked:
        if ranks.world > 1:
            raise TrainError("stacked seeds run in one process: not under torchrun")
        stacking.check_stackable(model_config, options.bf16)
    seeds = (run, *run.stacked)
    if run.stacked:  # one stream for every seed's lines: each says which seed it is
        seeds = tuple(stacking.seed_progress(r) for r in seeds)
    sessions = [open_session(r, options, model_config, rl, ranks) for r in seeds]
    while not all(s.done for s in sessions):
        behind = min(s.trainer.frames for s in sessions if not s.done)
        group = [s for s in sessions if not s.done and s.trainer.frames == behind]
        if len(group) > 1:
            stacked_update([s.trainer for s in group])
        else:
            group[0].trainer.update()
        for s in group:
            after_update(s, ranks)
    distributed.finish(ranks)
    for s in sessions:
        finish_session(s, ranks)
    return run.directory


def open_session(
    run: Run, options: TrainOptions, model_config: models.ModelConfig, rl: bool, ranks: distributed.Ranks
) -> Session:
    """A run's trainer, resumed from its last.pt where there is one (refused when it is another run's),
    its metrics.csv cut to the resume point."""
    progress = run.progress if ranks.main else (lambda line: None)
    trainer = Trainer(run, options, model_config, rl, ranks)
    last, metrics_path = run.directory / "last.pt", run.directory / "metrics.csv"
    if last.exists():
        ck = load_checkpoint(last)
        record = {
            "method": run.method,
            "options": asdict(options),
            "kitchens": list(trainer.kitchens),
            "seed": run.seed,
            "frames": run.frames,
        }
        differ = checkpoint_differences(ck, record)
        if ck["model_config"] != asdict(trainer.model_config):
            differ.append("model_config")
        if differ:
            raise TrainError(
                f"{last} is not this run's checkpoint (it differs in {'; '.join(differ[:4])}); "
                f"delete {run.directory} to start over"
            )
        try:
            trainer.load_state_dict(ck)
        except (KeyError, ValueError, RuntimeError, TypeError) as e:
            raise TrainError(f"checkpoint {last} does not fit this run ({type(e).__name__}: {e})") from e
        progress(f"resumed {run.directory} from {last.name} at {trainer.frames:,} frames")
    seconds_before = 0.0  # the resume point's row's
    if ranks.main:
        kept = read_metrics_rows(metrics_path, trainer.frames)
        atomic_write(metrics_path, _csv_text(kept))
        if trainer.frames:
            seconds_before = seconds_at(kept, trainer.frames)
            if seconds_before is None:
                progress(
                    f"{metrics_path} has no training time at {trainer.frames:,} frames; it counts from now"
                )
                seconds_before = 0.0
    agents = trainer.total_agents if rl or trainer.dagger else 0
    on_ranks = f" on {ranks.world} ranks" if ranks.world > 1 else ""
    stacked = f", seed {run.seed} of {len(run.stacked) + 1} stacked" if run.stacked else ""
    progress(
        f"training {run.method} on {len(trainer.kitchens)} kitchens "
        f"({len(trainer.space.target_ids)} targets, "
        f"{agents} agents{on_ranks}{stacked}) to {run.frames:,} frames; run {run.directory}"
    )
    keep, frames = options.keep_every, trainer.frames
    return Session(
        run, trainer, progress, seconds_before,
        next_log=(frames // options.log_every + 1) * options.log_every,
        next_val=(frames // options.val_every + 1) * options.val_every,
        next_keep=(frames // keep + 1) * keep if keep else None,
        f0=frames,
    )  # fmt: skip


def after_update(s: Session, ranks: distributed.Ranks) -> None:
    """After an update: the time estimate, a snapshot, and every log_every frames the ranks' numbers
    summed, validation (every val_every, and at the end; best.pt), the metrics row, last.pt and the
    progress line."""
    announce_rate(s)
    keep_snapshot(s, ranks)
    if s.trainer.frames < s.next_log and not s.done:
        return
    s.next_log = (s.trainer.frames // s.trainer.opts.log_every + 1) * s.trainer.opts.log_every
    ranks_state = reduce_ranks(s.trainer, ranks)
    if not ranks.main:  # rank 0 alone validates and writes
        return
    validation = validate_and_select(s)
    row = write_metrics_row(s, validation)
    save_checkpoint(
        s.run.directory / "last.pt",
        {**s.trainer.state_dict(), **({"ranks": ranks_state} if ranks.world > 1 else {})},
    )
    report_progress(s, row)


def announce_rate(s: Session) -> None:
    """Once, ESTIMATE_AFTER seconds in: the rate so far and the time it gives to the end."""
    trainer = s.trainer
    if s.estimated or time.perf_counter() - s.t0 < ESTIMATE_AFTER or s.done:
        return
    s.estimated = True
    rate = (trainer.frames - s.f0) / (time.perf_counter() - s.t0)
    if rate > 0:
        s.progress(
            f"  {rate:,.0f} frames/s over the first {trainer.frames - s.f0:,} frames: about "
            f"{duration_text((s.run.frames - trainer.frames) / rate)} to go at that rate (later "
            "episodes are longer; the progress lines give the ETA as it goes)"
        )


def keep_snapshot(s: Session, ranks: distributed.Ranks) -> None:
    """Every keep_every frames (rank 0): the weights as snapshots/frames-N.pt."""
    trainer = s.trainer
    if s.next_keep is None or trainer.frames < s.next_keep or not ranks.main:
        return
    keep = trainer.opts.keep_every
    s.next_keep = (trainer.frames // keep + 1) * keep
    snapshots = s.run.directory / "snapshots"
    snapshots.mkdir(exist_ok=True)
    save_checkpoint(snapshots / f"frames-{trainer.frames}.pt", trainer.policy_state())


def reduce_ranks(trainer: Trainer, ranks: distributed.Ranks):
    """Every rank's episode and loss numbers summed into rank 0's; the other ranks' counters start
    afresh. -> every rank's state for last.pt (None with one rank)."""
    trainer.stats = distributed.sum_numbers(trainer.stats, ranks)
    if ranks.world > 1:
        trainer.target_stats = distributed.sum_tensor(torch.from_numpy(trainer.target_stats), ranks).numpy()
    ranks_state = distributed.gather(trainer.rank_state(), ranks) if ranks.world > 1 else None
    if not ranks.main:
        trainer.stats = trainer._empty_stats()
        trainer.target_stats[:] = 0.0
    return ranks_state


def validate_and_select(s: Session) -> tuple[float, float, int]:
    """Every val_every frames, and at the end: validation, and best.pt where its SR is the best so far
    (the paper's rule; ties to the later). -> SR, SPL, episodes (NaN, NaN, 0 between validations)."""
    trainer, options = s.trainer, s.trainer.opts
    if trainer.frames < s.next_val and not s.done:
        return float("nan"), float("nan"), 0
    s.next_val = (trainer.frames // options.val_every + 1) * options.val_every
    started = time.perf_counter()
    val_sr, val_spl, val_frames, val_episodes = trainer.validate()
    trainer.val_max = max(trainer.val_max, val_sr)
    selected = val_sr >= trainer.best_val_sr
    s.progress(
        f"  validation: SR {val_sr:.1f}% (standard error {standard_error(val_sr, val_episodes):.1f}, "
        f"{val_episodes} episodes), SPL {val_spl:.1f}% ({val_frames:,} frames in "
        f"{time.perf_counter() - started:.1f} s){'; now best.pt' if selected else ''}"
    )
    if selected:
        trainer.best_val_sr = val_sr
        save_checkpoint(
            s.run.directory / "best.pt", {**trainer.state_dict(), "val_sr": val_sr, "val_spl": val_spl}
        )
    return val_sr, val_spl, val_episodes


def write_metrics_row(s: Session, validation: tuple[float, float, int]) -> dict:
    """The metrics row since the last one (appended to metrics.csv); the counters start afresh."""
    trainer = s.trainer
    val_sr, val_spl, val_episodes = validation
    seconds = time.perf_counter() - s.t0
    row = _metrics_row(trainer, s.seconds_before, seconds, trainer.frames - s.f0, val_sr, val_spl)
    row["val_episodes"] = val_episodes or ""
    with open(s.run.directory / "metrics.csv", "a") as f:
        csv.DictWriter(f, METRICS).writerow(row)
    trainer.stats = trainer._empty_stats()
    trainer.target_stats[:] = 0.0
    return row


def report_progress(s: Session, row: dict) -> None:
    """The progress line of a metrics row, with the time to the end at the session's rate."""
    trainer = s.trainer
    fps = (trainer.frames - s.f0) / max(time.perf_counter() - s.t0, 1e-9)
    eta = f"  ETA {duration_text((s.run.frames - trainer.frames) / fps)}" if not s.done and fps > 0 else ""
    s.progress(
        f"{trainer.frames:>12,} frames  {row['frames_per_s']:>8} frames/s{eta}  "
        f"reward/frame {row['mean_reward']}  "
        f"SR(training episodes, mean over targets) {row['success_rate']}%  "
        f"losses RL {row['rl_loss']} IL {row['il_loss']} "
        f"TSE {row['tse_loss']}"
    )


def finish_session(s: Session, ranks: distributed.Ranks) -> None:
    """finished.json: the frames, the selected checkpoint's validation SR and the training time."""
    if not ranks.main:
        return
    trainer = s.trainer
    finished = {
        "frames": trainer.frames,
        "best_val_sr": trainer.best_val_sr,
        "best_rule": BEST_RULE,
        "seconds": s.seconds_before + time.perf_counter() - s.t0,
    }
    atomic_write(s.run.directory / "finished.json", json.dumps(finished) + "\n")
    s.progress(
        f"finished {s.run.method}: {trainer.frames:,} frames, best validation SR {trainer.best_val_sr:.1f}%"
    )


def _metrics_row(
    trainer: Trainer, seconds_before: float, seconds: float, frames_done: int, val_sr: float, val_spl: float
) -> dict:
    """One metrics.csv row: `seconds` is the training time of the whole run (the sessions before a
    resume included), `frames_per_s` this session's rate."""
    s = trainer.stats
    episodes, successes = trainer.target_stats
    per_target = successes[episodes > 0] / episodes[episodes > 0]

    def mean(total: str, count: str) -> str:
        return f"{s[total] / s[count]:.4f}" if s[count] else ""

    return {
        "frames": trainer.frames,
        "seconds": f"{seconds_before + seconds:.1f}",
        "frames_per_s": f"{frames_done / max(seconds, 1e-9):.0f}",
        "updates": trainer.updates,
        "episodes": int(s["episodes"]),
        "mean_reward": mean("reward", "frames"),
        "mean_return": mean("returns", "episodes"),
        "success_rate": f"{100 * per_target.mean():.2f}" if len(per_target) else "",
        "episode_success_rate": f"{100 * s['successes'] / s['episodes']:.2f}" if s["episodes"] else "",
        "rl_loss": mean("rl", "losses_rl"),
        "il_loss": mean("il", "losses_il"),
        "tse_loss": mean("tse", "losses_tse"),
        "val_sr": "" if math.isnan(val_sr) else f"{val_sr:.2f}",
        "val_spl": "" if math.isnan(val_spl) else f"{val_spl:.2f}",
    }
