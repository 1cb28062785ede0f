"""Stage 15 — rollout: the acting half of training. The training agents, everything they carry from one
rollout to the next, and `Actors.collect`: n steps of every agent under the current weights, without
autograd, returned as a `Rollout` for the learning half (kgnavbench/train.py) to replay.

What the agents carry between rollouts, all of it saved in a checkpoint so that a resumed run acts
exactly as an unbroken one:
- the batched navigators (kgnavbench/vecenv.py, without autoreset: a finished agent's next episode
  is drawn only after the TSE has read where it ended) and their episode generator;
- each agent's LSTM state, or FF A3C's last frames;
- the TSE's sub-target sampler (kgnavbench/losses.py) and the step counter it timestamps with.
The action sampler (a torch generator) is the trainer's: IL draws its batches from the same stream.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from .agent import Model, detached, keep_rows, rows_of
from .graph import STOP
from .losses import SubtargetSampler, subtarget_types
from .models import N_ACTIONS
from .runs import TrainOptions
from .vecenv import NavigationVectorEnv, StateSpace


class PassInputs(NamedTuple):
    """One acting forward pass's inputs: `Model.__call__`'s arguments less the graph."""

    space: StateSpace
    states: np.ndarray  # (B,) the agents' states
    goals: np.ndarray  # (B,) their destinations' states
    hidden: tuple | None  # the LSTM state (h, c) before this step; None for FF A3C (no LSTM)
    scene: np.ndarray | None  # FF's training-kitchen index per agent
    history: np.ndarray | None  # FF's frames


@dataclass
class Cut:
    """The agents a time limit cut at one step, and the forward pass that values the states they
    reached (the return goes on past the cap: `Actors.add_cut_value`)."""

    agents: np.ndarray  # their rows
    inputs: PassInputs


def answer(model: Model, inputs: PassInputs, graph):
    """One acting forward pass of one model: (logits, value, hidden, extras)."""
    return model(
        inputs.space, inputs.states, inputs.goals, inputs.hidden, graph, inputs.scene, inputs.history
    )


@dataclass
class Rollout:
    """n steps of B agents as acting saw them (`Actors.collect`); the learning pass replays them."""

    states: np.ndarray  # (n, B) the state each step acted in
    targets: np.ndarray  # (n, B) its target row
    actions: np.ndarray  # (n, B)
    reached: np.ndarray  # (n, B) the state each step reached (before a new episode began)
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


class Actors:
    """The training agents of one process (its rank's share under torchrun) in all its kitchens.

    `collect` is a rollout, read top to bottom: `start_rollout`, then per step the model's answer to
    `step_inputs` handed to `step` (act, step the agents, score, TSE, episode ends), the agents a time
    limit cut valued (`add_cut_value`), and `end_rollout` with the bootstrap value. stacking.collect
    runs the same steps for a row's seeds with their forward passes stacked."""

    def __init__(
        self,
        space: StateSpace,
        kitchen: np.ndarray,
        assigned: np.ndarray | None,
        options: TrainOptions,
        model: Model,
        generator: torch.Generator,
        seed: int,
        reach: int | None,
    ):
        """The agents of `kitchen` (one entry per agent: its training kitchen's index in `space`), each
        keeping its target of `assigned` (None: a new target every episode), stepped by one
        NavigationVectorEnv under the training options (episode cap, when a wrong Stop ends an
        episode); `model` acts for them, sampling with `generator`; `seed` seeds their episodes;
        `reach` is the start curriculum's farthest start now (None: none)."""
        self.space, self.opts, self.generator = space, options, generator
        self.device = model.device
        self.ff = model.config.arch == "ff"
        self.envs = NavigationVectorEnv.over(
            space,
            kitchen,
            assigned=assigned,
            stop_ends=options.stop_ends_from == 0,
            max_steps=options.episode_cap,
            autoreset_mode="disabled",
            observe=False,
        )
        self.envs.reset(seed=seed, options={"reach": reach})
        # episodes, TSE sub-targets and their batches draw from this one stream, which the checkpoint saves
        self.rng = self.envs.np_random
        # the simulator's state: the trainer (not a plugin) indexes its feature tables, the TSE and the
        # co-visibility counts by the agents' true states
        self.nav = self.envs.navigators
        self.hidden = model.net.initial_state(self.nav.n, model.device)
        self.history_length = model.config.history
        self.history = np.repeat(self.nav.state[:, None], self.history_length, 1) if self.ff else None
        self.tick = 0  # steps of the run (every agent steps at each tick)
        lstm_size = model.config.lstm if not self.ff else 0
        self.tse = SubtargetSampler(self.nav.n, options.tse_subtargets, options.tse_window, lstm_size)
        self.subtarget_types = subtarget_types(space)

    def collect(self, model: Model, graph, reach: int | None, stats: dict, per_target: np.ndarray) -> Rollout:
        """n steps of every agent, without autograd (acting needs no graph): what they saw and did,
        and the acting pass's logits and values. The rewards and ended episodes are added to `stats`
        (totals) and `per_target` (2, targets: episodes, successes per target row); the ended ones' TSE
        windows come with the rollout, and its agent's next episode (starting at most `reach` actions
        from its destination) begins at the next step. stacking.collect runs the same loop for a
        row's seeds, with their forward passes stacked."""
        act = partial(answer, model, graph=graph)
        with torch.no_grad():
            rollout = self.start_rollout()
            for t in range(self.opts.n_steps):
                logits, value, hidden, _ = act(self.step_inputs())
                cut = self.step(rollout, t, logits, value, hidden, reach, stats, per_target)
                if cut is not None:
                    self.add_cut_value(rollout, t, cut, act(cut.inputs)[1])
            return self.end_rollout(rollout, act(self.step_inputs())[1])

    def start_rollout(self) -> Rollout:
        """An empty rollout of n steps, from the agents' LSTM state now."""
        n, b, device = self.opts.n_steps, self.nav.n, self.device
        self.hidden = detached(self.hidden)
        steps = partial(np.zeros, (n, b))
        return Rollout(
            states=steps(np.int64),
            targets=steps(np.int64),
            actions=steps(np.int64),
            reached=steps(np.int64),
            rewards=steps(np.float32),
            dones=steps(np.float32),
            truncated=steps(bool),
            histories=np.zeros((n, b, self.history_length), np.int64) if self.ff else None,
            scene=self.nav.kitchen if self.ff else None,
            start_hidden=self.hidden,
            bootstrap=torch.zeros(b, device=device),  # end_rollout's
            logits=torch.zeros(n, b, N_ACTIONS, device=device),
            values=torch.zeros(n, b, device=device),
            windows=[],
        )

    def step_inputs(self) -> PassInputs:
        """The forward pass every agent needs now: at a step, or for the bootstrap value after the last."""
        nav = self.nav
        scene = nav.kitchen if self.ff else None
        return PassInputs(
            self.space, nav.state, self.space.destination[nav.target], self.hidden, scene, self.history
        )

    def step(
        self, rollout: Rollout, t: int, logits, value, hidden, reach, stats: dict, per_target
    ) -> Cut | None:
        """Step t of the rollout, given the acting pass's answer for it (`step_inputs`): sample the
        actions, step the agents, score them, feed the TSE, end and restart the finished episodes
        and carry the LSTM state on. Returns the agents a time limit cut (None: none), whose rewards
        still lack gamma V of the states they reached."""
        opts, nav, space = self.opts, self.nav, self.space
        rollout.states[t], rollout.targets[t] = nav.state, nav.target
        if self.ff:
            rollout.histories[t] = self.history
        before_hidden = self.hidden
        rollout.logits[t], rollout.values[t] = logits, value
        probs = F.softmax(logits, -1)
        action = torch.multinomial(probs, 1, generator=self.generator).squeeze(1)
        a = action.cpu().numpy()
        rollout.actions[t] = a
        before = nav.state.copy()
        _, r, terminated, truncated, infos = self.envs.step(a)
        rollout.reached[t] = nav.state
        if opts.wrong_stop_penalty:
            r = r - opts.wrong_stop_penalty * ((a == STOP) & ~nav.success)
        done = terminated | truncated
        stats["reward"] += float(r.sum())
        rollout.rewards[t], rollout.dones[t] = r, done
        agents = np.flatnonzero(truncated & ~terminated)
        cut = self._cut(rollout, t, agents, hidden) if len(agents) else None
        if opts.tse:
            candidate = (a != STOP) & (space.objects[nav.state] & self.subtarget_types[nav.target]).any(1)
            taken = probs.gather(1, action[:, None]).squeeze(1).cpu().numpy()
            lstm_state = None
            if before_hidden is not None:
                lstm_state = torch.stack(before_hidden, 1).float().cpu().numpy()
            self.tse.step(self.tick, before, a, taken, nav.state, candidate, self.rng, lstm_state)
        self.tick += 1
        finished = np.flatnonzero(done)
        if len(finished):
            self._end_episodes(rollout, finished, done, infos["final_info"], reach, stats, per_target)
        self.hidden = keep_rows(hidden, torch.from_numpy(~done).to(self.device).float())
        if self.ff:
            self.history = np.concatenate([self.history[:, 1:], nav.state[:, None]], 1)
            self.history[finished] = nav.state[finished, None]
        return cut

    def _cut(self, rollout: Rollout, t: int, agents: np.ndarray, hidden) -> Cut:
        """The agents a time limit cut at step t. A time limit is no end of the task: the return goes on
        past the cap, so the last step's reward gains gamma V(the state it reached), as Stable-Baselines3
        does (the episode still ends here: nothing after it belongs to it). The pass's inputs are taken
        now, before the episode restarts."""
        nav, space, scene = self.nav, self.space, rollout.scene
        rollout.truncated[t, agents] = True
        history = None
        if self.ff:
            history = np.concatenate([self.history[agents, 1:], nav.state[agents, None]], 1)
        return Cut(
            agents,
            PassInputs(
                space,
                nav.state[agents],
                space.destination[nav.target[agents]],
                rows_of(hidden, agents),
                None if scene is None else scene[agents],
                history,
            ),
        )

    def _end_episodes(self, rollout, finished, done, ended: dict, reach, stats: dict, per_target) -> None:
        """The episodes that ended at this step counted (`stats`, `per_target`), their TSE windows kept
        for this update's relabelling, and their agents' next episodes begun."""
        nav = self.nav
        stats["episodes"] += len(finished)
        stats["successes"] += int(ended["success"][finished].sum())
        np.add.at(per_target[0], nav.target[finished], 1.0)
        np.add.at(per_target[1], nav.target[finished], ended["success"][finished])
        stats["returns"] += float(ended["episode_return"][finished].sum())
        if self.opts.tse:
            rollout.windows += self.tse.finish(finished, self.tick)
        self.envs.reset(options={"reset_mask": done, "reach": reach})

    def add_cut_value(self, rollout: Rollout, t: int, cut: Cut, value: torch.Tensor) -> None:
        """The cut agents' step-t rewards gain gamma V(the state each reached)."""
        rollout.rewards[t, cut.agents] += self.opts.gamma * value.cpu().numpy()

    def end_rollout(self, rollout: Rollout, bootstrap: torch.Tensor) -> Rollout:
        """The rollout, with V of the state after its last step."""
        rollout.bootstrap = bootstrap
        return rollout

    # -- checkpoints: what differs between the ranks, with the trainer's generators --------------------
    def state_dict(self) -> dict:
        return {
            "agents": self.nav.state_dict(),
            "hidden": self.hidden,
            "history": None if self.history is None else torch.from_numpy(self.history.copy()),
            "tse": self.tse.state_dict(),
        }

    def load_state_dict(self, ck: dict, device: torch.device) -> None:
        self.nav.load_state_dict(ck["agents"])
        self.hidden = None if ck["hidden"] is None else tuple(h.to(device) for h in ck["hidden"])
        self.history = None if ck["history"] is None else ck["history"].numpy().copy()
        self.tse.load_state_dict(ck["tse"])
