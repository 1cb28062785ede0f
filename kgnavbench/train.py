"""Stage 14 — train: the learned methods' trainer. A synchronous batched A2C with the paper's A3C losses,
imitation learning (IL), target skill extension (TSE), checkpoints, logs and resumption.

It stands on the stages before it: the run directory, options and checkpoints (kgnavbench/runs.py),
the batched navigators over all training kitchens' state graphs as one (kgnavbench/vecenv.py: a step
is a handful of NumPy gathers through the env's own `transition`), the losses and the IL and TSE data
(kgnavbench/losses.py), and the network with its inputs around it (kgnavbench/agent.py). Read it
top to bottom:

1. `Trainer`: the rollout (20 steps of all agents, then one learning pass over them), the IL and TSE
   passes, validation on fixed episodes, and the checkpoint (model, optimiser, every RNG, every agent's
   episode and LSTM state, the co-visibility counts): a run killed at any moment resumes from
   `last.pt` exactly as if it had never stopped. Under torchrun each rank holds its share of the
   agents (kgnavbench/distributed.py).
2. `learn`: the loop, `metrics.csv`, progress lines, `last.pt`, `best.pt` (Table I's checkpoint rule,
   the paper's words: the checkpoint with the highest validation SR, ties to the later one) and, with
   keep_every, weight snapshots.
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
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import distributed, encoder, models
from .agent import Model, detached, keep_rows, rows_of, run_episodes
from .env import reward
from .files import atomic_write, duration_text
from .graph import STOP
from .kitchens import KITCHEN_NAMES
from .losses import (
    Sequences,
    SubtargetSampler,
    actor_critic_loss,
    assign_targets,
    expert_sequences,
    imitation_loss,
    n_step_returns,
    optimal_action_loss,
    optimal_actions,
    pad,
    relabel,
    subtarget_types,
)
from .models import N_ACTIONS
from .runs import (
    CHECKPOINT_FORMAT,
    POLICY_KEYS,
    Run,
    TrainError,
    TrainOptions,
    checkpoint_differences,
    load_checkpoint,
    save_checkpoint,
)
from .tasks import load_task_file
from .vecenv import NavigationVectorEnv, StateSpace, build_space, curriculum_reach

VALIDATION_CAP = 1000  # validation kitchens are unseen kitchens: evaluate's cap of 1000 actions
# FF A3C is validated where its scene-specific heads exist: its own training kitchens' seen targets,
# evaluate's cap for them, from start states drawn with this seed offset, never a fixed episode's start
SEEN_VALIDATION_CAP = 100
# how best.pt was chosen, in finished.json: runs finished before it was written (no "best_rule") kept
# the latest checkpoint within one standard error of the best so far (`within_one_standard_error`)
BEST_RULE = "highest validation SR, ties to the later"
FF_VALIDATION_SEED = 0xFFA3C
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
# 1. The trainer


@dataclass
class Rollout:
    """n steps of B agents as acting saw them (`Trainer.collect`); the learning pass replays them."""

    states: np.ndarray  # (n, B) the state each step acted in
    targets: np.ndarray  # (n, B) its target row
    actions: np.ndarray  # (n, B)
    # (n, B) the env's rewards (less a wrong Stop's penalty); a step that reached the cap also gains
    # gamma V(the state it reached)
    rewards: np.ndarray
    dones: np.ndarray  # (n, B) 1.0 where the episode ended at that step, by the task or by the cap
    truncated: np.ndarray  # (n, B) True where it ended by the cap only
    histories: np.ndarray | None  # (n, B, history) FF's frames
    scene: np.ndarray | None  # (B,) FF's training-kitchen index
    start_hidden: tuple | None  # the LSTM state before the first step
    bootstrap: torch.Tensor  # (B,) V of the state after the last step
    logits: torch.Tensor  # (n, B, 10) the acting pass's
    values: torch.Tensor  # (n, B)
    windows: list  # TSE: the sub-target windows (losses.Window) of the episodes that ended


class Trainer:
    """A2C over all training kitchens at once, with optional IL and TSE; its whole state checkpoints."""

    def __init__(
        self,
        run: Run,
        options: TrainOptions,
        model_config: models.ModelConfig,
        rl: bool,
        ranks: distributed.Ranks = distributed.SINGLE,
    ):
        self.run, self.opts, self.rl, self.ranks = run, options, rl, ranks
        self.kitchens = list(run.kitchens)
        self.model_config = dataclasses.replace(model_config, n_scenes=len(self.kitchens))
        self.ff = self.model_config.arch == "ff"
        self.space = build_space(
            self.kitchens, "seen", options.success_rule, self.model_config.pixels, options.tse_unseen_targets
        )
        # seeded after build_space: encoding features on a cache miss draws from torch's generator
        torch.manual_seed(run.seed)
        net = models.make_model(self.model_config)
        if net.encoder is not None:  # end to end: start from the committed encoder and its statistics
            net.encoder.load_state_dict(encoder.load_encoder().state_dict())
            stats = encoder.encoder_feature_stats()
            net.feature_mean.copy_(stats["mean"])
            net.feature_std.copy_(stats["std"])
        self.device = torch.device(run.device)
        net.to(self.device)
        self.model = Model(net, self.model_config, models.CoVisibility(), options.bf16, self.device)
        self.optimizer = torch.optim.Adam(net.parameters(), lr=options.lr)
        # every rank starts from the same weights (above); its agents draw from generators of their own
        # (rank 0's are a single process's)
        seed = run.seed if ranks.rank == 0 else run.seed + 1_000_003 * ranks.rank
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
        kitchen = np.repeat(np.arange(len(self.kitchens)), options.agents_per_kitchen)
        assigned = None
        if options.fixed_targets:
            assigned = assign_targets(self.space, kitchen, options.targets_per_kitchen)
        mine = np.arange(self.total_agents)[ranks.rank :: ranks.world]  # this rank's share of the agents
        if not len(mine):
            raise TrainError(f"{self.total_agents} agents cannot be shared by {ranks.world} ranks")
        n_agents = len(mine)
        # the public vector env without autoreset: a finished agent's next episode is drawn after the
        # TSE has read where it ended. Its generator is the trainer's: episodes, TSE sub-targets and
        # their batches draw from one stream, which the checkpoint saves.
        self.envs = NavigationVectorEnv.over(
            self.space,
            kitchen[mine],
            assigned=None if assigned is None else assigned[mine],
            stop_ends=options.stop_ends_from == 0,
            max_steps=options.episode_cap,
            autoreset_mode="disabled",
            observe=False,
        )
        self.envs.reset(seed=seed, options={"reach": self.reach()})
        self.rng = self.envs.np_random
        # the simulator's state: the trainer (not a plugin) indexes its feature tables, the TSE and the
        # co-visibility counts by the agents' true states
        self.nav = self.envs.navigators
        self.hidden = net.initial_state(n_agents, self.device)
        self.history = np.repeat(self.nav.state[:, None], self.model_config.history, 1) if self.ff else None
        # TSE: the sub-targets sampled per episode; a rollout hands the windows of the episodes that
        # ended in it to the update's relabelling
        self.tick = 0  # steps of the run (every agent steps at each tick)
        lstm_size = self.model_config.lstm if not self.ff else 0
        self.tse = SubtargetSampler(n_agents, options.tse_subtargets, options.tse_window, lstm_size)
        self.subtarget_types = subtarget_types(self.space)
        self.il = options.il or not rl
        self.dagger = self.il and options.il_expert == "dagger"
        self.experts = (
            expert_sequences(
                self.space, options.il_expert, options.il_walk, np.random.default_rng([run.seed, 1])
            )
            if self.il and not self.dagger
            else None
        )
        if self.experts is not None and options.targets_per_kitchen:  # only the trained targets' experts
            kept = np.unique(assigned)
            ex = self.experts
            self.experts = Sequences(ex.states[kept], ex.actions[kept], ex.mask[kept], ex.goal[kept])

    @staticmethod
    def _empty_stats() -> dict:
        keys = (
            "frames", "reward", "episodes", "successes", "returns", "rl", "il", "tse",
            "losses_rl", "losses_il", "losses_tse",
        )  # fmt: skip
        return dict.fromkeys(keys, 0.0)

    # -- one update ------------------------------------------------------------------------------
    def update(self) -> None:
        """One rollout of every agent (or, IL only, one expert batch) and one gradient step."""
        graph = self.model.graph()
        loss = torch.zeros((), device=self.device)
        windows: list = []  # TSE: the sub-target windows of the episodes that end in this rollout
        imitate = self.il and (not self.rl or self.frames < self.opts.il_fraction * self.run.frames)
        self.envs.stop_ends = self.opts.stop_ends_from is not None and self.frames >= self.opts.stop_ends_from
        if self.rl or self.dagger:
            rl_loss, il_loss, windows = self.rollout(graph, imitate and self.dagger)
            if self.rl:
                loss = loss + rl_loss
                self.stats["rl"] += rl_loss.item()
                self.stats["losses_rl"] += 1
            if il_loss is not None:
                loss = loss + self.opts.il_weight * il_loss
                self.stats["il"] += il_loss.item()
                self.stats["losses_il"] += 1
        if imitate and not self.dagger:
            il_loss, n_frames = self.imitation(graph)
            loss = loss + self.opts.il_weight * il_loss
            self.stats["il"] += il_loss.item()
            self.stats["losses_il"] += 1
            if not self.rl:
                self.stats["frames"] += n_frames  # this rank's (metrics sum the ranks')
                self.frames += int(distributed.sum_tensor(torch.tensor(n_frames), self.ranks))
        if self.rl and self.opts.tse:
            tse_loss = self.skill_extension(graph, windows)
            if tse_loss is not None:
                loss = loss + self.opts.tse_weight * tse_loss
                self.stats["tse"] += tse_loss.item()
                self.stats["losses_tse"] += 1
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        distributed.average_gradients(self.model.net.parameters(), self.ranks)
        torch.nn.utils.clip_grad_norm_(self.model.net.parameters(), self.opts.max_grad_norm)
        self.optimizer.step()
        self.updates += 1
        distributed.check_replicas(self.model.net.parameters(), self.ranks, self.updates)

    def collect(self, graph) -> Rollout:
        """n steps of every agent, without autograd (acting needs no graph): what they saw and did,
        and the acting pass's logits and values. The ended episodes' TSE windows come with it; new
        episodes are drawn in the rollout itself."""
        opts, nav, space = self.opts, self.nav, self.space
        n, b = opts.n_steps, nav.n
        states = np.zeros((n, b), np.int64)
        targets = np.zeros((n, b), np.int64)
        actions = np.zeros((n, b), np.int64)
        reached = np.zeros((n, b), np.int64)  # the state each step reached (before a new episode began)
        histories = np.zeros((n, b, self.model_config.history), np.int64) if self.ff else None
        rewards = np.zeros((n, b), np.float32)
        dones = np.zeros((n, b), np.float32)
        truncations = np.zeros((n, b), bool)
        logits_seen = torch.zeros(n, b, N_ACTIONS, device=self.device)
        values_seen = torch.zeros(n, b, device=self.device)
        windows = []
        start_hidden = hidden = detached(self.hidden)
        scene = nav.kitchen if self.ff else None
        with torch.no_grad():
            for t in range(n):
                states[t], targets[t] = nav.state, nav.target
                if self.ff:
                    histories[t] = self.history
                goals = space.destination[nav.target]
                before_hidden = hidden
                logits, value, hidden, _ = self.model(
                    space, nav.state, goals, hidden, graph, scene, self.history
                )
                logits_seen[t], values_seen[t] = logits, value
                probs = F.softmax(logits, -1)
                action = torch.multinomial(probs, 1, generator=self.generator).squeeze(1)
                a = action.cpu().numpy()
                actions[t] = a
                before = nav.state.copy()
                _, r, terminated, truncated, infos = self.envs.step(a)
                reached[t] = nav.state
                if opts.wrong_stop_penalty:
                    r = r - opts.wrong_stop_penalty * ((a == STOP) & ~nav.success)
                done = terminated | truncated
                self.stats["reward"] += float(r.sum())
                rewards[t], dones[t] = r, done
                cut = np.flatnonzero(truncated & ~terminated)
                if len(cut):
                    # a time limit is no end of the task: the return goes on past the cap, so the
                    # last step's reward gains gamma V(the state it reached), as Stable-Baselines3 does
                    # (the episode still ends here: nothing after it belongs to it)
                    truncations[t, cut] = True
                    history = None
                    if self.ff:
                        history = np.concatenate([self.history[cut, 1:], nav.state[cut, None]], 1)
                    _, after, _, _ = self.model(
                        space,
                        nav.state[cut],
                        space.destination[nav.target[cut]],
                        rows_of(hidden, cut),
                        graph,
                        None if scene is None else scene[cut],
                        history,
                    )
                    rewards[t, cut] += opts.gamma * after.cpu().numpy()
                if opts.tse:
                    candidate = (a != STOP) & (
                        space.objects[nav.state] & self.subtarget_types[nav.target]
                    ).any(1)
                    taken = probs.gather(1, action[:, None]).squeeze(1).cpu().numpy()
                    lstm_state = None
                    if before_hidden is not None:
                        lstm_state = torch.stack(before_hidden, 1).float().cpu().numpy()
                    self.tse.step(self.tick, before, a, taken, nav.state, candidate, self.rng, lstm_state)
                self.tick += 1
                finished = np.flatnonzero(done)
                if len(finished):
                    ended = infos["final_info"]
                    self.stats["episodes"] += len(finished)
                    self.stats["successes"] += int(ended["success"][finished].sum())
                    np.add.at(self.target_stats[0], nav.target[finished], 1.0)
                    np.add.at(self.target_stats[1], nav.target[finished], ended["success"][finished])
                    self.stats["returns"] += float(ended["episode_return"][finished].sum())
                    if opts.tse:  # the ended episodes' sub-targets, for this update's relabelling
                        windows += self.tse.finish(finished, self.tick)
                    self.envs.reset(options={"reset_mask": done, "reach": self.reach()})
                hidden = keep_rows(hidden, self.model.tensor(~done).float())
                if self.ff:
                    self.history = np.concatenate([self.history[:, 1:], nav.state[:, None]], 1)
                    self.history[finished] = nav.state[finished, None]
            goals = space.destination[nav.target]
            _, bootstrap, _, _ = self.model(space, nav.state, goals, hidden, graph, scene, self.history)
        self.hidden = hidden
        if self.model.uses_graph:
            covis = self.model.covis
            if self.ranks.world == 1:
                covis.add(space.objects[reached.reshape(-1)])
            else:  # every rank's frames count, on every rank
                before = covis.counts.clone()
                covis.add(space.objects[reached.reshape(-1)])
                covis.counts = before + distributed.sum_tensor(covis.counts - before, self.ranks)
        self.frames += n * self.total_agents  # every rank's agents stepped n times
        self.stats["frames"] += n * b  # this rank's (metrics sum the ranks')
        return Rollout(
            states, targets, actions, rewards, dones, truncations, histories, scene, start_hidden,
            bootstrap, logits_seen, values_seen, windows,
        )  # fmt: skip

    def rollout(self, graph, imitate: bool = False) -> tuple[torch.Tensor, torch.Tensor | None, list]:
        """n steps of every agent (`collect`), then the learning pass over them; returns the A2C loss
        of the rollout, when `imitate` the cross-entropy of the teacher's actions on every visited
        state (DAgger), and (TSE) the sub-target windows of the episodes that ended. `Model.unroll`
        replays the rollout's states with autograd, the non-recurrent layers once for all n x B rows,
        which costs far fewer small operations than a graph built step by step."""
        opts, space = self.opts, self.space
        ro = self.collect(graph)
        n, b = ro.states.shape
        keep = self.model.tensor(1.0 - ro.dones)
        goals = space.destination[ro.targets]
        logits, values = self.model.unroll(
            space, ro.states, goals, ro.start_hidden, keep, graph, ro.scene, ro.histories
        )
        log_p = F.log_softmax(logits, -1)
        taken = log_p.gather(2, self.model.tensor(ro.actions)[..., None]).squeeze(2)
        entropies = -(log_p.exp() * log_p).sum(-1)
        tensor = self.model.tensor
        returns = n_step_returns(tensor(ro.rewards), tensor(ro.dones), ro.bootstrap, opts.gamma)
        loss, _ = actor_critic_loss(taken, values, entropies, returns, opts.value_weight, opts.entropy)
        il = None
        if imitate:
            optimal, known = optimal_actions(space, ro.targets.reshape(-1), ro.states.reshape(-1))
            il = optimal_action_loss(log_p.reshape(n * b, -1), optimal, known).mean()
        return loss, il, ro.windows

    def reach(self) -> int | None:
        """The curriculum's farthest start (actions from the destination) at this frame; None: off or over."""
        return curriculum_reach(self.frames, self.opts.start_curriculum * self.run.frames)

    def subtrajectories(self, windows: list) -> Sequences | None:
        """Up to tse_batch of the sub-target windows of the episodes that ended during a rollout,
        relabelled; the rest are dropped. `Sequences.hidden` holds the LSTM state each relabelled
        episode starts from: the one the agent had there."""
        if not windows:
            return None
        take = self.rng.choice(len(windows), min(self.opts.tse_batch, len(windows)), replace=False)
        seqs, goals, rewards, behaviour, hidden = [], [], [], [], []
        for j in sorted(take):
            states, actions, probs, goal, start, stop = windows[j]
            # the relabelled episode starts after the window's last Stop: in the task "reach the
            # sub-target and Stop" that Stop ended the episode (a failure), so the walk after it is
            # the whole episode; keeping it would reward a wrong Stop with the sub-target's +10. The
            # failure itself (tse_failures) is a one-step episode: Stop where it stopped, -0.01.
            # (Only where training's wrong Stop is a no-op: where it ends the episode, no window holds one.)
            stops = np.flatnonzero(actions == STOP)
            if len(stops):
                last = stops[-1]
                if self.opts.tse_failures and states[last] != goal:
                    seqs.append(([int(states[last])], [STOP]))
                    goals.append(goal)
                    rewards.append(reward(np.zeros(1, bool), np.zeros(1, bool)))
                    behaviour.append(probs[last : last + 1].astype(np.float64))
                    hidden.append(stop)
                states, actions, probs = states[last + 1 :], actions[last + 1 :], probs[last + 1 :]
            if len(actions) == 0:
                continue
            s, a, r, mu = relabel(list(states) + [goal], actions, probs, goal)
            seqs.append((s, a))
            goals.append(goal)
            rewards.append(r)
            behaviour.append(mu)
            hidden.append(start)
        if not seqs:
            return None
        seq = pad(seqs, goals)
        seq.rewards = np.zeros(seq.states.shape, np.float32)
        seq.behaviour = np.full(seq.states.shape, np.nan)
        for i, (r, mu) in enumerate(zip(rewards, behaviour)):
            seq.rewards[i, : len(r)], seq.behaviour[i, : len(mu)] = r, mu
        seq.hidden = np.stack(hidden)  # (N, 2, lstm)
        return seq

    def sequence_pass(self, seq: Sequences, graph):
        """A separate pass of the model over padded sequences, from the LSTM states `seq.hidden` (zeros
        where None): logits (L, N, 10), values (L, N)."""
        n, length = seq.states.shape
        states = np.ascontiguousarray(seq.states.T)
        goals = np.broadcast_to(seq.goal, (length, n))
        history = None
        if self.ff:  # the last `history` states of each step, the first state repeated before it
            back = np.arange(length)[:, None] - np.arange(self.model_config.history)[::-1]
            history = np.ascontiguousarray(np.transpose(seq.states[:, np.clip(back, 0, None)], (1, 0, 2)))
        scene = self.space.kitchen_of[seq.states[:, 0]] if self.ff else None
        hidden = self.model.net.initial_state(n, self.device)
        if hidden is not None and seq.hidden is not None:
            start = self.model.tensor(seq.hidden)
            hidden = (start[:, 0].to(hidden[0].dtype), start[:, 1].to(hidden[1].dtype))
        return self.model.unroll(self.space, states, goals, hidden, None, graph, scene, history)

    def imitation(self, graph) -> tuple[torch.Tensor, int]:
        """Cross-entropy on il_batch expert trajectories drawn at random."""
        ex = self.experts
        n = len(ex.goal)
        order = torch.randperm(n, generator=self.generator, device=self.device)
        take = order[: min(self.opts.il_batch, n)].sort().values.cpu().numpy()
        seq = Sequences(ex.states[take], ex.actions[take], ex.mask[take], ex.goal[take])
        last = int(seq.mask.sum(1).max())
        seq = Sequences(seq.states[:, :last], seq.actions[:, :last], seq.mask[:, :last], seq.goal)
        logits, _ = self.sequence_pass(seq, graph)
        mask = self.model.tensor(seq.mask.T.astype(np.float32))
        return imitation_loss(logits, self.model.tensor(seq.actions.T), mask), int(seq.mask.sum())

    def skill_extension(self, graph, windows: list) -> torch.Tensor | None:
        """A2C's loss on the rollout's relabelled sub-trajectories (whole episodes: Monte-Carlo
        returns), optionally with truncated importance weights min(1, pi/mu)."""
        seq = self.subtrajectories(windows)
        if seq is None:
            return None
        logits, values = self.sequence_pass(seq, graph)
        log_p = F.log_softmax(logits, -1)
        tensor = self.model.tensor
        actions = tensor(seq.actions.T)
        taken = log_p.gather(2, actions[..., None]).squeeze(2)
        entropy = -(log_p.exp() * log_p).sum(-1)
        mask = tensor(seq.mask.T.astype(np.float32))
        rewards = tensor(seq.rewards.T)
        dones = torch.zeros_like(rewards)
        dones[tensor(seq.mask.sum(1) - 1), torch.arange(len(seq.goal), device=self.device)] = 1.0
        returns = n_step_returns(
            rewards, dones, torch.zeros(len(seq.goal), device=self.device), self.opts.gamma
        )
        weights = None
        if self.opts.tse_importance:
            # min(1, pi/mu) on the steps the agent took. The appended Stop has no mu (the agent never
            # took it there) and keeps weight 1: it is the relabelled task's one demonstration of
            # success, and weighting it by pi would scale its gradient by pi(Stop), least where it
            # is most needed
            mu = tensor(seq.behaviour.T).float()
            ratio = (taken.detach().exp() / mu).clamp(max=1.0)
            weights = torch.where(torch.isnan(mu), torch.ones_like(ratio), ratio)
        loss, _ = actor_critic_loss(
            taken, values, entropy, returns, self.opts.value_weight, self.opts.entropy, weights, mask
        )
        return loss

    # -- validation ------------------------------------------------------------------------------
    def validate(self) -> tuple[float, float, int, int]:
        """SR and SPL (percent) on the validation kitchens' fixed episodes (the first val_episodes per
        target), cap 1000, under the success rule, the frames and the episodes it took; its own seeded
        sampling, so training is untouched."""
        if self.val_space is None:
            names = load_task_file()["splits"]["val"][: self.opts.val_kitchens]
            self.val_space = build_space(
                sorted(names, key=KITCHEN_NAMES.index),
                "all",
                self.opts.success_rule,
                self.model_config.pixels,
            )
        sp = self.val_space
        rows = [(r, s) for r, starts in enumerate(sp.fixed_starts) for s in starts[: self.opts.val_episodes]]
        targets = np.array([r for r, _ in rows], np.int64)
        starts = np.array([s for _, s in rows], np.int64)
        if self.ff:
            targets, starts = self.ff_validation_episodes(len(rows))
            scene = self.space.target_kitchen[targets]
            sr, spl, frames = run_episodes(
                self.model, self.space, targets, starts, SEEN_VALIDATION_CAP, self.run.seed, scene
            )
            return sr, spl, frames, len(targets)
        sr, spl, frames = run_episodes(self.model, sp, targets, starts, VALIDATION_CAP, self.run.seed)
        return sr, spl, frames, len(rows)

    def ff_validation_episodes(self, at_least: int) -> tuple[np.ndarray, np.ndarray]:
        """FF A3C's validation episodes (Zhu et al. had no validation rooms, and its heads exist for its
        training kitchens only): the seen targets of its training kitchens that have a training start
        besides their fixed evaluation episodes' (a small kitchen's target can have none: 7 of the
        paper preset's 140, six in FloorPlan25 and one in FloorPlan29), as many episodes each as make
        at least `at_least` in all (the other rows' validation count), from those starts, drawn with
        the run's own seed. The same every time."""
        sp = self.space
        pools = []
        for r in range(len(sp.target_ids)):
            pool = sp.start_flat[sp.start_ptr[r] : sp.start_ptr[r + 1]]
            pools.append(pool[~np.isin(pool, sp.fixed_starts[r])])
        kept = [r for r, pool in enumerate(pools) if len(pool)]
        if not kept:
            raise TrainError("no training target has a training start outside the fixed episodes")
        per_target = -(-at_least // len(kept))
        rng = np.random.default_rng([FF_VALIDATION_SEED, self.run.seed])
        targets, starts = [], []
        for r in kept:
            starts.append(rng.choice(pools[r], per_target, replace=len(pools[r]) < per_target))
            targets.append(np.full(per_target, r, np.int64))
        return np.concatenate(targets), np.concatenate(starts).astype(np.int64)

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
            "tick": self.tick,
            "best_val_sr": float(self.best_val_sr),
            "val_max": float(self.val_max),
            "stats": {k: float(v) for k, v in self.stats.items()},
            "target_stats": torch.from_numpy(self.target_stats.copy()),
            "model": self.model.net.state_dict() if weights else None,
            "optimizer": self.optimizer.state_dict() if weights else None,
            "covis": self.model.covis.state_dict(),
            "rng": {
                "numpy": json.dumps(self.rng.bit_generator.state),  # plain data: weights_only loads it
                "sampling": self.generator.get_state(),
                "torch": torch.get_rng_state(),
                "python": random.getstate(),
            },
            "agents": self.nav.state_dict(),
            "hidden": self.hidden,
            "history": None if self.history is None else torch.from_numpy(self.history.copy()),
            "tse": self.tse.state_dict(),
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
        self.rng.bit_generator.state = json.loads(ck["rng"]["numpy"])
        self.generator.set_state(ck["rng"]["sampling"])
        torch.set_rng_state(ck["rng"]["torch"])
        random.setstate(ck["rng"]["python"])
        self.nav.load_state_dict(ck["agents"])
        self.hidden = None if ck["hidden"] is None else tuple(h.to(self.device) for h in ck["hidden"])
        self.history = None if ck["history"] is None else ck["history"].numpy().copy()
        self.tse.load_state_dict(ck["tse"])
        self.frames, self.updates, self.tick = ck["frames"], ck["updates"], ck["tick"]
        self.best_val_sr, self.stats = ck["best_val_sr"], dict(ck["stats"])
        self.val_max = ck.get("val_max", self.best_val_sr)
        if "target_stats" in ck:
            self.target_stats = ck["target_stats"].numpy().copy()


# ------------------------------------------------------------------------------------------------
# 2. The loop: logs, checkpoints, resumption


def standard_error(sr: float, episodes: int) -> float:
    """The binomial standard error (points) of an SR in percent measured on `episodes` episodes."""
    p = min(max(sr / 100.0, 0.0), 1.0)
    return 100.0 * math.sqrt(p * (1.0 - p) / max(episodes, 1))


def within_one_standard_error(val_sr: float, val_max: float, episodes: int) -> bool:
    """The one-standard-error reading of the checkpoint rule, as a replay over metrics.csv (the trainer
    keeps the best, the paper's words): a validation SR within one standard error of the best so far
    (val_max, this one included) would select its checkpoint, the latest such one kept."""
    return val_sr >= val_max - standard_error(val_max, episodes)


def _read_metrics(path: Path, up_to: int) -> list[dict]:
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


def _seconds_at(rows: list[dict], frames: int) -> float | None:
    """The training time metrics.csv's rows give at a frame count (a resume point), if one does."""
    for row in reversed(rows):
        try:
            if int(row["frames"]) == frames:
                seconds = float(row.get("seconds") or "nan")
                return seconds if math.isfinite(seconds) and seconds >= 0 else None
        except (KeyError, ValueError):
            return None
    return None


def _csv_text(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, METRICS)
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def learn(run: Run, options: TrainOptions, model_config: models.ModelConfig, rl: bool = True) -> Path:
    """Train (or resume) a run: A2C (rl=True) with IL and TSE as the options say, or IL alone."""
    options.check()
    torch.set_num_threads(options.threads)
    ranks = distributed.start(torch.device(run.device))
    progress = run.progress if ranks.main else (lambda line: None)
    trainer = Trainer(run, options, model_config, rl, ranks)
    last, best = run.directory / "last.pt", run.directory / "best.pt"
    metrics_path = run.directory / "metrics.csv"
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
    seconds_before = 0.0  # the training time of the sessions before a resume: the resume point's row's
    if ranks.main:
        kept = _read_metrics(metrics_path, trainer.frames)
        atomic_write(metrics_path, _csv_text(kept))
        if trainer.frames:
            seconds_before = _seconds_at(kept, trainer.frames)
            if seconds_before is None:
                progress(
                    f"{metrics_path} has no training time at {trainer.frames:,} frames; it counts from now"
                )
                seconds_before = 0.0
    every = options.log_every
    next_log = (trainer.frames // every + 1) * every
    next_val = (trainer.frames // options.val_every + 1) * options.val_every
    agents = trainer.total_agents if rl or trainer.dagger else 0
    on_ranks = f" on {ranks.world} ranks" if ranks.world > 1 else ""
    progress(
        f"training {run.method} on {len(trainer.kitchens)} kitchens "
        f"({len(trainer.space.target_ids)} targets, "
        f"{agents} agents{on_ranks}) to {run.frames:,} frames; run {run.directory}"
    )
    keep = options.keep_every
    next_keep = (trainer.frames // keep + 1) * keep if keep else None
    t0, f0 = time.perf_counter(), trainer.frames
    while trainer.frames < run.frames:
        trainer.update()
        if next_keep is not None and trainer.frames >= next_keep and ranks.main:
            next_keep = (trainer.frames // keep + 1) * keep
            snapshots = run.directory / "snapshots"
            snapshots.mkdir(exist_ok=True)
            save_checkpoint(snapshots / f"frames-{trainer.frames}.pt", trainer.policy_state())
        done = trainer.frames >= run.frames
        if trainer.frames < next_log and not done:
            continue
        next_log = (trainer.frames // every + 1) * every
        val_sr = val_spl = float("nan")
        val_episodes = 0
        trainer.stats = distributed.sum_numbers(trainer.stats, ranks)  # every rank's episodes and losses
        if ranks.world > 1:
            trainer.target_stats = distributed.sum_tensor(
                torch.from_numpy(trainer.target_stats), ranks
            ).numpy()
        ranks_state = distributed.gather(trainer.rank_state(), ranks) if ranks.world > 1 else None
        if not ranks.main:  # rank 0 alone validates and writes
            trainer.stats = trainer._empty_stats()
            trainer.target_stats[:] = 0.0
            continue
        if trainer.frames >= next_val or done:
            next_val = (trainer.frames // options.val_every + 1) * options.val_every
            tv = time.perf_counter()
            val_sr, val_spl, val_frames, val_episodes = trainer.validate()
            trainer.val_max = max(trainer.val_max, val_sr)
            selected = val_sr >= trainer.best_val_sr  # the paper's rule: the best; ties to the later
            progress(
                f"  validation: SR {val_sr:.1f}% (standard error {standard_error(val_sr, val_episodes):.1f}, "
                f"{val_episodes} episodes), SPL {val_spl:.1f}% ({val_frames:,} frames in "
                f"{time.perf_counter() - tv:.1f} s){'; now best.pt' if selected else ''}"
            )
            if selected:
                trainer.best_val_sr = val_sr
                save_checkpoint(best, {**trainer.state_dict(), "val_sr": val_sr, "val_spl": val_spl})
        row = _metrics_row(
            trainer, seconds_before, time.perf_counter() - t0, trainer.frames - f0, val_sr, val_spl
        )
        row["val_episodes"] = val_episodes or ""
        with open(metrics_path, "a") as f:
            csv.DictWriter(f, METRICS).writerow(row)
        trainer.stats = trainer._empty_stats()
        trainer.target_stats[:] = 0.0
        save_checkpoint(last, {**trainer.state_dict(), **({"ranks": ranks_state} if ranks.world > 1 else {})})
        fps = (trainer.frames - f0) / max(time.perf_counter() - t0, 1e-9)
        eta = f"  ETA {duration_text((run.frames - trainer.frames) / fps)}" if not done and fps > 0 else ""
        progress(
            f"{trainer.frames:>12,} frames  {row['frames_per_s']:>8} frames/s{eta}  "
            f"reward/frame {row['mean_reward']}  "
            f"SR(training episodes, mean over targets) {row['success_rate']}%  "
            f"losses RL {row['rl_loss']} IL {row['il_loss']} "
            f"TSE {row['tse_loss']}"
        )
    seconds = seconds_before + time.perf_counter() - t0
    distributed.finish(ranks)
    if not ranks.main:
        return run.directory
    atomic_write(
        run.directory / "finished.json",
        json.dumps(
            {
                "frames": trainer.frames,
                "best_val_sr": trainer.best_val_sr,
                "best_rule": BEST_RULE,
                "seconds": seconds,
            }
        )
        + "\n",
    )
    progress(
        f"finished {run.method}: {trainer.frames:,} frames, best validation SR {trainer.best_val_sr:.1f}%"
    )
    return run.directory


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
