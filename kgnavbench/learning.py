"""Stage 16 — learning: the learning half of training, as plain functions of the model and the data.
The losses of one update (kgnavbench/train.py's `Trainer.loss`): a rollout's A2C loss (and DAgger's
labels on its states), IL's cross-entropy on a batch of expert trajectories, TSE's A2C loss on the
relabelled windows of the episodes that ended during the rollout. The losses themselves and the IL and
TSE data are kgnavbench/losses.py's; here the model replays the states (`Model.unroll`, and the
packed sequence pass for IL's and TSE's sequences of different lengths).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .agent import Model
from .env import reward
from .graph import STOP
from .losses import (
    Sequences,
    actor_critic_loss,
    imitation_loss,
    n_step_returns,
    optimal_action_loss,
    optimal_actions,
    pad,
    relabel,
)
from .rollout import Rollout
from .runs import TrainOptions
from .vecenv import StateSpace


def rollout_losses(
    model: Model, space: StateSpace, ro: Rollout, graph, opts: TrainOptions, imitate: bool, replayed=None
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The A2C loss of a rollout and, when `imitate`, the cross-entropy of the teacher's actions on
    every visited state (DAgger). `Model.unroll` replays the rollout's states with autograd, the
    non-recurrent layers once for all n x B rows, which costs far fewer small operations than a graph
    built step by step while acting (`replayed`: its logits and values, from a stacked pass)."""
    n, b = ro.states.shape
    if replayed is None:
        replayed = model.unroll(
            space, ro.states, space.destination[ro.targets], ro.start_hidden,
            model.tensor(1.0 - ro.dones), graph, ro.scene, ro.histories,
        )  # fmt: skip
    logits, values = replayed
    log_p = F.log_softmax(logits, -1)
    taken = log_p.gather(2, model.tensor(ro.actions)[..., None]).squeeze(2)
    entropies = -(log_p.exp() * log_p).sum(-1)
    returns = n_step_returns(model.tensor(ro.rewards), model.tensor(ro.dones), ro.bootstrap, opts.gamma)
    loss, _ = actor_critic_loss(taken, values, entropies, returns, opts.value_weight, opts.entropy)
    il = None
    if imitate:
        optimal, known = optimal_actions(space, ro.targets.reshape(-1), ro.states.reshape(-1))
        il = optimal_action_loss(log_p.reshape(n * b, -1), optimal, known).mean()
    return loss, il


def expert_batch_loss(
    model: Model, space: StateSpace, experts: Sequences, batch: int, generator: torch.Generator, graph
) -> tuple[torch.Tensor, int]:
    """IL: the cross-entropy on `batch` expert trajectories drawn at random, and the frames they hold."""
    n = len(experts.goal)
    order = torch.randperm(n, generator=generator, device=model.device)
    take = order[: min(batch, n)].sort().values.cpu().numpy()
    ex = experts
    seq = Sequences(ex.states[take], ex.actions[take], ex.mask[take], ex.goal[take])
    last = int(seq.mask.sum(1).max())
    seq = Sequences(seq.states[:, :last], seq.actions[:, :last], seq.mask[:, :last], seq.goal)
    logits, _ = sequence_pass(model, space, seq, graph)
    mask = model.tensor(seq.mask.T.astype(np.float32))
    return imitation_loss(logits, model.tensor(seq.actions.T), mask), int(seq.mask.sum())


def relabelled_windows(windows: list, opts: TrainOptions, rng: np.random.Generator) -> Sequences | None:
    """TSE: up to tse_batch of the sub-target windows of the episodes that ended during a rollout,
    relabelled; the rest are dropped. `Sequences.hidden` holds the LSTM state each relabelled
    episode starts from: the one the agent had there."""
    if not windows:
        return None
    take = rng.choice(len(windows), min(opts.tse_batch, len(windows)), replace=False)
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
            if opts.tse_failures and states[last] != goal:
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


def skill_extension_loss(
    model: Model, space: StateSpace, seq: Sequences, graph, opts: TrainOptions
) -> torch.Tensor:
    """TSE: A2C's loss on relabelled sub-trajectories (whole episodes: Monte-Carlo returns),
    optionally with truncated importance weights min(1, pi/mu)."""
    logits, values = sequence_pass(model, space, seq, graph)
    log_p = F.log_softmax(logits, -1)
    tensor = model.tensor
    actions = tensor(seq.actions.T)
    taken = log_p.gather(2, actions[..., None]).squeeze(2)
    entropy = -(log_p.exp() * log_p).sum(-1)
    mask = tensor(seq.mask.T.astype(np.float32))
    rewards = tensor(seq.rewards.T)
    dones = torch.zeros_like(rewards)
    dones[tensor(seq.mask.sum(1) - 1), torch.arange(len(seq.goal), device=model.device)] = 1.0
    returns = n_step_returns(rewards, dones, torch.zeros(len(seq.goal), device=model.device), opts.gamma)
    weights = None
    if opts.tse_importance:
        # min(1, pi/mu) on the steps the agent took. The appended Stop has no mu (the agent never
        # took it there) and keeps weight 1: it is the relabelled task's one demonstration of
        # success, and weighting it by pi would scale its gradient by pi(Stop), least where it
        # is most needed
        mu = tensor(seq.behaviour.T).float()
        ratio = (taken.detach().exp() / mu).clamp(max=1.0)
        weights = torch.where(torch.isnan(mu), torch.ones_like(ratio), ratio)
    loss, _ = actor_critic_loss(
        taken, values, entropy, returns, opts.value_weight, opts.entropy, weights, mask
    )
    return loss


def sequence_pass(model: Model, space: StateSpace, seq: Sequences, graph):
    """A separate pass of the model over padded sequences (IL's, TSE's), from the LSTM states
    `seq.hidden` (zeros where None): logits (L, N, 10), values (L, N)."""
    n, length = seq.states.shape
    states = np.ascontiguousarray(seq.states.T)
    goals = np.broadcast_to(seq.goal, (length, n))
    history, scene = None, None
    if (
        model.config.arch == "ff"
    ):  # the last `history` states of each step, the first state repeated before it
        back = np.arange(length)[:, None] - np.arange(model.config.history)[::-1]
        history = np.ascontiguousarray(np.transpose(seq.states[:, np.clip(back, 0, None)], (1, 0, 2)))
        scene = space.kitchen_of[seq.states[:, 0]]
    hidden = model.net.initial_state(n, model.device)
    if hidden is None:
        return model.unroll(space, states, goals, hidden, None, graph, scene, history)
    if seq.hidden is not None:
        start = model.tensor(seq.hidden)
        hidden = (start[:, 0].to(hidden[0].dtype), start[:, 1].to(hidden[1].dtype))
    # the real steps only (each sequence's mask is a prefix): no work on the padding
    return model.unroll_sequences(space, states, goals, seq.mask.sum(1), hidden, graph)
