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

import numpy as np
import torch
import torch.nn.functional as F

from .agent import Model, detached, keep_rows, rows_of
from .graph import STOP
from .losses import SubtargetSampler, subtarget_types
from .models import N_ACTIONS
from .runs import TrainOptions
from .vecenv import NavigationVectorEnv, StateSpace


@dataclass
class Forward:
    """A forward pass `Actors.steps` needs: `inputs` are `Model.__call__`'s arguments less the graph
    (space, states, goals, hidden, scene, history). "step": every agent, at a step or for the bootstrap
    value after the last; "cut": the agents a time limit cut, for gamma V of the state they reached."""

    kind: str
    inputs: tuple


def answer(model: Model, request: Forward, graph):
    """A `Forward` answered by one model: (logits, value, hidden, extras)."""
    space, states, goals, hidden, scene, history = request.inputs
    return model(space, states, goals, hidden, graph, scene, history)


def drive(steps: list, cut, step) -> list:
    """`Actors.steps` generators run to their rollouts in lock-step, one forward pass at a time: each
    "cut" request answered alone by `cut(i, request)`, then the "step" requests of all at once by
    `step(requests)` (a list of answers). `Actors.collect` drives one; `stacking.collect` a row's
    seeds, their step passes stacked. The generators take the same steps, so they end together."""
    done: list = [None] * len(steps)

    def send(i: int, reply) -> Forward | None:
        try:
            return steps[i].send(reply)
        except StopIteration as end:
            done[i] = end.value
            return None

    requests = [next(s) for s in steps]
    while True:
        for i in range(len(steps)):
            while requests[i] is not None and requests[i].kind == "cut":
                requests[i] = send(i, cut(i, requests[i]))
        live = [r is not None for r in requests]
        if not any(live):
            return done
        if not all(live):
            raise RuntimeError("lock-stepped actors out of step")
        for i, reply in enumerate(step(requests)):
            requests[i] = send(i, reply)


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
    """The training agents of one process (its rank's share under torchrun) in all its kitchens."""

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
        from its destination) begins at the next step."""
        steps = self.steps(model, reach, stats, per_target)
        with torch.no_grad():
            alone = partial(answer, model, graph=graph)
            [rollout] = drive([steps], lambda i, request: alone(request), lambda one: [alone(one[0])])
        return rollout

    def steps(self, model: Model, reach: int | None, stats: dict, per_target: np.ndarray):
        """`collect` as a generator that yields each forward pass it needs (a `Forward`) and is sent
        the model's answer, (logits, value, hidden, extras); it returns the Rollout. Several seeds'
        actors step in lock-step through it, their forward passes stacked into one
        (kgnavbench/stacking.py); `collect` answers each with the model itself."""
        opts, nav, space = self.opts, self.nav, self.space
        n, b = opts.n_steps, nav.n
        states = np.zeros((n, b), np.int64)
        targets = np.zeros((n, b), np.int64)
        actions = np.zeros((n, b), np.int64)
        reached = np.zeros((n, b), np.int64)
        histories = np.zeros((n, b, self.history_length), np.int64) if self.ff else None
        rewards = np.zeros((n, b), np.float32)
        dones = np.zeros((n, b), np.float32)
        truncations = np.zeros((n, b), bool)
        logits_seen = torch.zeros(n, b, N_ACTIONS, device=model.device)
        values_seen = torch.zeros(n, b, device=model.device)
        windows = []
        start_hidden = hidden = detached(self.hidden)
        scene = nav.kitchen if self.ff else None
        for t in range(n):
            states[t], targets[t] = nav.state, nav.target
            if self.ff:
                histories[t] = self.history
            goals = space.destination[nav.target]
            before_hidden = hidden
            logits, value, hidden, _ = yield Forward(
                "step", (space, nav.state, goals, hidden, scene, self.history)
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
            stats["reward"] += float(r.sum())
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
                _, after, _, _ = yield Forward(
                    "cut",
                    (
                        space,
                        nav.state[cut],
                        space.destination[nav.target[cut]],
                        rows_of(hidden, cut),
                        None if scene is None else scene[cut],
                        history,
                    ),
                )
                rewards[t, cut] += opts.gamma * after.cpu().numpy()
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
                ended = infos["final_info"]
                stats["episodes"] += len(finished)
                stats["successes"] += int(ended["success"][finished].sum())
                np.add.at(per_target[0], nav.target[finished], 1.0)
                np.add.at(per_target[1], nav.target[finished], ended["success"][finished])
                stats["returns"] += float(ended["episode_return"][finished].sum())
                if opts.tse:  # the ended episodes' sub-targets, for this update's relabelling
                    windows += self.tse.finish(finished, self.tick)
                self.envs.reset(options={"reset_mask": done, "reach": reach})
            hidden = keep_rows(hidden, model.tensor(~done).float())
            if self.ff:
                self.history = np.concatenate([self.history[:, 1:], nav.state[:, None]], 1)
                self.history[finished] = nav.state[finished, None]
        goals = space.destination[nav.target]
        _, bootstrap, _, _ = yield Forward("step", (space, nav.state, goals, hidden, scene, self.history))
        self.hidden = hidden
        return Rollout(
            states, targets, actions, reached, rewards, dones, truncations, histories, scene, start_hidden,
            bootstrap, logits_seen, values_seen, windows,
        )  # fmt: skip

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
