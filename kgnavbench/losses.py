"""Stage 13 — losses: what the learner minimises, and the data of its imitation and skill-extension terms.

1. The losses. `n_step_returns`, `actor_critic_loss` (policy gradient, value loss with weight
   `value_weight`, entropy bonus; optional per-sample weights for TSE's importance weights),
   `optimal_action_loss` (DAgger's teacher: every optimal action of a visited state) and
   `imitation_loss` (cross-entropy on expert actions).
2. IL data: one expert trajectory per training target (`expert_sequences`; the paper's walk back from
   the destination, or a shortest path), padded into `Sequences`; `assign_targets` gives each agent
   its one training target, as the paper's threads.
3. TSE: `SubtargetSampler` samples, per episode, 5 sub-targets at random among the states that showed
   a novel object (a pickupable that is no target) or another agent's training target
   (`subtarget_types`); `relabel` makes each "reach this state and Stop", with its view as the target
   image, rewards recomputed and a final Stop worth +10; the LSTM state the agent had where the
   relabelled episode begins is kept with it. The sampler's arrays checkpoint (`state_dict`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from .env import reward
from .graph import STOP, optimal_action_mask, shortest_trajectory, walk_back_trajectory
from .runs import TrainError
from .tasks import MIN_START_DISTANCE
from .vecenv import StateSpace, arrays_state, load_arrays

# ------------------------------------------------------------------------------------------------
# 1. The losses


def n_step_returns(rewards: torch.Tensor, dones: torch.Tensor, bootstrap: torch.Tensor, gamma: float):
    """(T, B) rewards and done flags (the episode ended at that step), (B,) value of the state after
    the last step: R_t = r_t + gamma * R_{t+1} * (1 - done_t), R_T = bootstrap."""
    returns = torch.empty_like(rewards)
    running = bootstrap
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = rewards[t] + gamma * running * (1.0 - dones[t])
        returns[t] = running
    return returns


def actor_critic_loss(
    log_prob: torch.Tensor,
    value: torch.Tensor,
    entropy: torch.Tensor,
    returns: torch.Tensor,
    value_weight: float,
    entropy_weight: float,
    weights: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict]:
    """A3C's loss over any batch of (taken action's log-prob, value, entropy, return): policy gradient
    with advantage R - V (weighted per sample by `weights`: TSE's importance weights), value loss
    0.5 (R - V)^2 with weight alpha, minus the entropy bonus; `mask` drops padding."""
    mask = torch.ones_like(value) if mask is None else mask
    weights = torch.ones_like(value) if weights is None else weights
    n = mask.sum().clamp(min=1.0)
    advantage = (returns - value).detach()
    policy = -(weights * log_prob * advantage * mask).sum() / n
    value_loss = 0.5 * (((returns - value) ** 2) * mask).sum() / n
    bonus = (entropy * mask).sum() / n
    loss = policy + value_weight * value_loss - entropy_weight * bonus
    return loss, {"policy": policy.item(), "value": value_loss.item(), "entropy": bonus.item()}


def optimal_actions(
    space: StateSpace, targets: np.ndarray, states: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """On-policy IL's labels: for each agent the set of BFS-optimal actions (B, 10) — every action
    one step nearer the goal, or Stop on it — and whether the goal is reachable at all (B,). All of
    them, not one: BFS ties are common (a strafe or a turn), and a single tie-broken label asks the
    network to learn the tie-break."""
    now = space.dist[targets, states]
    return optimal_action_mask(now, space.dist[targets[:, None], space.next_state[states]]), now >= 0


def optimal_action_loss(log_p: torch.Tensor, optimal: np.ndarray, known: np.ndarray) -> torch.Tensor:
    """-log of the probability the policy gives to the optimal actions (B,), zero where unknown."""
    mask = torch.from_numpy(optimal).to(log_p.device)
    total = torch.logsumexp(log_p.masked_fill(~mask, float("-inf")), -1)
    return -torch.where(torch.from_numpy(known).to(log_p.device), total, torch.zeros_like(total))


def imitation_loss(logits: torch.Tensor, actions: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the expert's actions, padding masked out."""
    ce = F.cross_entropy(logits.reshape(-1, logits.shape[-1]), actions.reshape(-1), reduction="none")
    return (ce * mask.reshape(-1)).sum() / mask.sum().clamp(min=1.0)


# ------------------------------------------------------------------------------------------------
# 2. IL data and 3. TSE


@dataclass
class Sequences:
    """Padded sequences for a separate pass of the model: states[i, t] where actions[i, t] is taken,
    toward the goal state goal[i] (whose view is the target image)."""

    states: np.ndarray  # (N, L) global states
    actions: np.ndarray  # (N, L)
    mask: np.ndarray  # (N, L) bool, False on padding
    goal: np.ndarray  # (N,) global state: the target image's state
    rewards: np.ndarray | None = None  # (N, L)
    behaviour: np.ndarray | None = None  # (N, L) behaviour policy's probability (NaN: not taken by it)
    hidden: np.ndarray | None = None  # (N, 2, lstm) the LSTM state (h, c) before the first step; None: zeros


def pad(seqs: list[tuple[list[int], list[int]]], goals, extra=None) -> Sequences:
    n, length = len(seqs), max(len(a) for _, a in seqs)
    states = np.zeros((n, length), np.int64)
    actions = np.zeros((n, length), np.int64)
    mask = np.zeros((n, length), bool)
    for i, (s, a) in enumerate(seqs):
        states[i, : len(s)], actions[i, : len(a)], mask[i, : len(a)] = s, a, True
        states[i, len(s) :] = s[-1]
    return Sequences(states, actions, mask, np.asarray(goals, np.int64), **(extra or {}))


def expert_sequences(space: StateSpace, expert: str, walk: int, rng: np.random.Generator) -> Sequences:
    """One expert trajectory per target of the space: the paper's walk-back from the destination (a
    walk of 10..`walk` steps, its length drawn by rng: "to a random start"; reversed), or the
    BFS-optimal path from a training start drawn by rng."""
    seqs = []
    for r in range(len(space.target_ids)):
        k = space.target_kitchen[r]
        off, kt = space.offsets[k], space.tasks[k]
        dest = int(space.destination[r])
        if expert == "walk_back":
            steps = int(rng.integers(min(MIN_START_DISTANCE, walk), walk + 1))
            start, actions = walk_back_trajectory(kt.graph, dest - off, steps)
            start += off
        else:
            lo, hi = space.start_ptr[r], space.start_ptr[r + 1]
            start = int(space.start_flat[lo + rng.integers(hi - lo)])
            actions = shortest_trajectory(space.next_state, space.dist[r], start)
        states = [int(start)]
        for a in actions[:-1]:
            states.append(int(space.next_state[states[-1], a]))
        if not space.goal[r, states[-1]]:
            raise TrainError(f"the {expert} expert of {space.target_ids[r]} does not end at its destination")
        seqs.append((states, actions))
    return pad(seqs, space.destination)


def assign_targets(space: StateSpace, kitchen: np.ndarray, per_kitchen: int = 0) -> np.ndarray:
    """One training target per agent, as the paper's threads: the j-th agent of a kitchen trains its
    kitchen's target j mod (targets of the kitchen; only its first `per_kitchen` when not 0). Every
    target needs an agent."""
    kitchen = np.asarray(kitchen, np.int64)
    assigned = np.empty(len(kitchen), np.int64)
    for k in range(len(space.kitchens)):
        rows = space.kitchen_rows[space.kitchen_ptr[k] : space.kitchen_ptr[k + 1]]
        rows = rows[:per_kitchen] if per_kitchen else rows
        agents = np.flatnonzero(kitchen == k)
        if len(agents) < len(rows):
            raise TrainError(
                f"{space.kitchens[k]} has {len(rows)} training targets but {len(agents)} agents: with "
                f"fixed_targets each target needs an agent (set agents_per_kitchen to at least {len(rows)}, "
                "or fixed_targets=false)"
            )
        assigned[agents] = rows[np.arange(len(agents)) % len(rows)]
    return assigned


def subtarget_types(space: StateSpace) -> np.ndarray:
    """(T, 125) per training target, the object types whose sight makes a state one of TSE's
    sub-targets for an agent training that target: novel objects (`tse_types`) and the kitchen's other
    training targets ("the targets trained by other threads"), never its own target's type."""
    n_types = space.objects.shape[1]
    own = np.zeros((len(space.kitchens), n_types), bool)
    own[space.target_kitchen, space.target_type] = True
    eligible = space.tse_types[space.target_kitchen] | own[space.target_kitchen]
    eligible[np.arange(len(space.target_ids)), space.target_type] = False
    return eligible


class Window(NamedTuple):
    """A sub-target sampled by TSE: the steps of its episode that led to it (states, actions and the
    behaviour policy's probabilities of those actions, chronological), the sub-target state, and the
    agent's LSTM state (h, c) (2, lstm) before the window's relabelled part begins (its first step, or
    the step after its last Stop) and before its last Stop (zeros where it holds none)."""

    states: np.ndarray
    actions: np.ndarray
    probs: np.ndarray
    goal: int
    hidden: np.ndarray
    stop_hidden: np.ndarray


class SubtargetSampler:
    """TSE's sub-targets, sampled as the paper: per agent and episode, `k` of the steps that reached a
    state showing a sub-target object (`subtarget_types`), drawn uniformly at random among all such
    steps of the episode (reservoir sampling, Algorithm R, so the whole episode need not be kept).
    Each kept step is stored with the window of at most `window` steps of its episode that led to it
    and the LSTM state the agent had where the relabelled episode begins, so that TSE replays it from
    the state the agent acted in, not from zeros in mid-episode; `finish` hands an ended episode's
    samples over for relabelling. Its arrays are its state."""

    FIELDS = ("ring_state", "ring_action", "ring_prob", "ring_hidden", "episode_tick", "count", "slot_state",
              "slot_action", "slot_prob", "slot_length", "slot_goal", "slot_hidden")  # fmt: skip

    def __init__(self, n_agents: int, k: int, window: int, hidden_size: int = 0):
        self.k, self.window = k, window
        shape = (n_agents, window)
        # the last `window` steps of every agent (column tick % window): state before, action, its prob,
        # the LSTM state (h, c) before the step
        self.ring_state = np.zeros(shape, np.int64)
        self.ring_action = np.zeros(shape, np.int64)
        self.ring_prob = np.zeros(shape, np.float64)
        self.ring_hidden = np.zeros((*shape, 2, hidden_size), np.float32)
        self.episode_tick = np.zeros(n_agents, np.int64)  # the tick of the episode's first step
        self.count = np.zeros(n_agents, np.int64)  # sub-target steps met in this episode
        self.slot_state = np.zeros((n_agents, k, window), np.int64)  # chronological, right-aligned
        self.slot_action = np.zeros((n_agents, k, window), np.int64)
        self.slot_prob = np.zeros((n_agents, k, window), np.float64)
        self.slot_length = np.zeros((n_agents, k), np.int64)
        self.slot_goal = np.zeros((n_agents, k), np.int64)
        # the LSTM states where the relabelled episode begins and before the window's last Stop
        self.slot_hidden = np.zeros((n_agents, k, 2, 2, hidden_size), np.float32)

    def step(
        self, tick, before, actions, probs, after, candidate, rng: np.random.Generator, hidden=None
    ) -> None:
        """Record one step of every agent; `candidate` marks the agents whose step reached a state
        showing a sub-target object (a Stop reaches nothing new: the caller leaves Stops out); `hidden`:
        the agents' LSTM states (h, c) before the step, (n_agents, 2, lstm) (None without an LSTM)."""
        column = tick % self.window
        self.ring_state[:, column], self.ring_action[:, column], self.ring_prob[:, column] = (
            before,
            actions,
            probs,
        )
        if hidden is not None:
            self.ring_hidden[:, column] = hidden
        idx = np.flatnonzero(candidate)
        if not len(idx) or not self.k:
            return
        self.count[idx] += 1
        m = self.count[idx]
        # Algorithm R: the m-th candidate fills slot m-1 while there is one, else replaces a random
        # slot with probability k/m
        slot = np.where(m <= self.k, m - 1, rng.integers(0, m))
        keep = slot < self.k
        idx, slot = idx[keep], slot[keep]
        if not len(idx):
            return
        length = np.minimum(self.window, tick - self.episode_tick[idx] + 1)
        columns = (tick - self.window + 1 + np.arange(self.window)) % self.window
        self.slot_state[idx, slot] = self.ring_state[idx][:, columns]
        self.slot_action[idx, slot] = self.ring_action[idx][:, columns]
        self.slot_prob[idx, slot] = self.ring_prob[idx][:, columns]
        self.slot_length[idx, slot] = length
        self.slot_goal[idx, slot] = after[idx]
        # where the relabelled episode begins: the window's first step, or the step after its last
        # Stop (`learning.relabelled_windows`); this step is no Stop, so that step lies in the window
        position = np.arange(self.window)
        stops = (self.slot_action[idx, slot] == STOP) & (position >= self.window - length[:, None])
        last_stop = np.where(stops.any(1), self.window - 1 - np.argmax(stops[:, ::-1], 1), -1)
        begin = np.maximum(self.window - length, last_stop + 1)
        self.slot_hidden[idx, slot, 0] = self.ring_hidden[idx, columns[begin]]
        self.slot_hidden[idx, slot, 1] = np.where(
            (last_stop >= 0)[:, None, None], self.ring_hidden[idx, columns[np.maximum(last_stop, 0)]], 0.0
        )

    def finish(self, idx: np.ndarray, next_tick: int) -> list[Window]:
        """The sampled windows of the agents whose episodes ended; their next episodes start at
        `next_tick` with nothing sampled."""
        out = []
        for i in idx:
            for j in range(min(int(self.count[i]), self.k)):
                n = int(self.slot_length[i, j])
                out.append(
                    Window(
                        self.slot_state[i, j, -n:].copy(),
                        self.slot_action[i, j, -n:].copy(),
                        self.slot_prob[i, j, -n:].copy(),
                        int(self.slot_goal[i, j]),
                        self.slot_hidden[i, j, 0].copy(),
                        self.slot_hidden[i, j, 1].copy(),
                    )
                )
        self.count[idx] = 0
        self.episode_tick[idx] = next_tick
        return out

    def state_dict(self) -> dict:
        return arrays_state(self, self.FIELDS)

    def load_state_dict(self, d: dict) -> None:
        load_arrays(self, self.FIELDS, d, "TSE's")


def relabel(states, actions, behaviour, goal: int) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """HER-style: a walk states[0] -a0-> states[1] ... -a_{m-1}-> states[m] == goal becomes the task
    "reach goal and Stop": the same actions plus a final Stop at goal, rewards recomputed with the
    env's reward function (goal = that one state), the Stop succeeding (+10). Returns states (m + 1),
    actions (m + 1), rewards (m + 1) and the behaviour probabilities (NaN for the added Stop)."""
    states, actions = [int(s) for s in states], [int(a) for a in actions]
    if states[-1] != goal or len(states) != len(actions) + 1:
        raise ValueError("relabel needs states[0..m] ending at the goal and m actions")
    after = np.array(states[1:] + [goal])
    on_goal = after == goal
    reached_before = np.concatenate([[states[0] == goal], np.logical_or.accumulate(on_goal)[:-1]])
    success = np.zeros(len(after), bool)
    success[-1] = True
    rewards = reward(on_goal & ~reached_before, success)
    return states, actions + [STOP], rewards, np.append(np.asarray(behaviour, np.float64), np.nan)
