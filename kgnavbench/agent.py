"""Stage 14 — agent: the actor-critic network with what it needs around it, and fixed episodes run
with it.

`Model` wraps a network (kgnavbench/models.py) with its device, its bf16 autocast, the knowledge
graph's co-visibility counts, and the gathers that turn state indices of a `vecenv.StateSpace` into
its inputs (the frozen encoder's features of the view and of each distinct target image, the visible
types); `forward` takes the inputs themselves, as the evaluation policy builds them from the env's
observations; `unroll` replays T steps of B agents for learning. `run_episodes` runs fixed episodes to
the end with the model's sampled actions (the trainer's validation). `rows_of`, `keep_rows` and
`detached` handle LSTM states (None for FF).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from . import models
from .vecenv import Navigators, StateSpace

# ------------------------------------------------------------------------------------------------
# The model around the network


def detached(hidden):
    return None if hidden is None else tuple(h.detach() for h in hidden)


def rows_of(hidden, idx):
    return None if hidden is None else tuple(h[idx] for h in hidden)


def keep_rows(hidden, keep: torch.Tensor):
    return None if hidden is None else tuple(h * keep.view(-1, *([1] * (h.dim() - 1))) for h in hidden)


class Model:
    """The actor-critic with what it needs around it: features and object vectors of a state space,
    the knowledge graph, frame histories (FF) and scene ids."""

    def __init__(self, net, config: models.ModelConfig, covis, bf16: bool, device="cpu"):
        self.net, self.config, self.covis, self.device = net, config, covis, torch.device(device)
        self.bf16 = bf16 or self.device.type == "cuda"  # bf16 autocast on CUDA; on the CPU as asked
        self.uses_graph = config.kg != "none" and config.kg_graph == "accumulated"
        self._space: tuple[int, torch.Tensor, torch.Tensor] | None = None  # a space's tables on the device

    def tensor(self, array) -> torch.Tensor:
        """A NumPy array as a tensor on the model's device (the array itself on the CPU)."""
        return torch.from_numpy(np.ascontiguousarray(array)).to(self.device)

    def autocast(self):
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16)

    def tables(self, space: StateSpace) -> tuple[torch.Tensor, torch.Tensor]:
        """The space's standardized features and object vectors on the device, moved once per space."""
        if self._space is None or self._space[0] != id(space):
            self._space = (id(space), space.features_t.to(self.device), space.objects_t.to(self.device))
        return self._space[1], self._space[2]

    def adjacency(self) -> torch.Tensor | None:
        if not self.uses_graph:
            return None
        return self.covis.adjacency(self.config.kg_edges).to(self.device)

    def graph(self):
        """The knowledge graph's per-update terms (models.GraphTerms), computed once for all the steps
        that share these weights and this adjacency; None without an accumulated graph."""
        adjacency = self.adjacency()
        if adjacency is None:
            return None
        with self.autocast():
            return self.net.graph_terms(adjacency)

    def inputs(self, space: StateSpace, states, goals, history=None):
        """The network's inputs for agents in `states` (or their frame `history` (..., H) for FF)
        toward the target images of `goals` (states): view features (or views), each distinct target's
        features (or view) once with the row of every agent's (None for FF: one per agent), and the
        visible-type vectors R_t and R_g. Any leading shape (B or T x B)."""
        features, objects = self.tables(space)
        s, g = self.tensor(states), self.tensor(goals)
        target_rows = None
        if self.config.arch == "lstm":
            distinct, rows = np.unique(goals, return_inverse=True)
            target_rows = self.tensor(rows.reshape(-1))
        else:
            distinct = goals
        if self.config.pixels:
            view = self.tensor(space.views[history if history is not None else states])
            target = self.tensor(space.views[distinct])
        else:
            view = features[self.tensor(history) if history is not None else s]
            target = features[self.tensor(distinct)]
        return view, target, target_rows, objects[s], objects[g]

    def __call__(self, space: StateSpace, states, goals, hidden, graph, scene=None, history=None):
        """One forward pass: agents in `states` (or their frame `history` (B, H) for FF) toward the
        target images of `goals` (states); `graph`: the knowledge graph's terms (`Model.graph`)."""
        view, target, target_rows, r_t, r_g = self.inputs(space, states, goals, history)
        return self.forward(view, target, target_rows, r_t, r_g, hidden, graph, scene)

    def forward(self, view, target, target_rows, r_t, r_g, hidden, graph, scene=None):
        """One forward pass on the network's inputs themselves (as `inputs` gives them; the evaluation
        policy builds them from the env's observations); scene: (B,) training-kitchen indices (FF)."""
        with self.autocast():
            logits, value, hidden, extras = self.net(
                view,
                target,
                r_t,
                r_g,
                hidden,
                graph=graph,
                scene=None if scene is None else self.tensor(scene),
                target_rows=target_rows,
            )
        return logits.float(), value.float(), hidden, extras

    def unroll(self, space: StateSpace, states, goals, hidden, keep, graph, scene=None, history=None):
        """The network over T steps of B agents at once, for learning: states and goals (T, B) (FF:
        history (T, B, H)), the LSTM state before the first step, keep (T, B) 0 where an episode ended
        at that step (the state is zeroed after it; None: no ends). The parts that do not recur run
        once over all T x B rows, only the LSTM steps through time. -> logits (T, B, 10), values (T, B)."""
        n, b = states.shape
        flat = history.reshape(n * b, -1) if history is not None else None
        view, target, target_rows, r_t, r_g = self.inputs(space, states.reshape(-1), goals.reshape(-1), flat)
        with self.autocast():
            joint, _ = self.net.encode(view, target, r_t, r_g, graph, target_rows)
            if self.config.arch != "lstm":
                scenes = self.tensor(np.tile(scene, n))
                logits, values, _ = self.net.act(joint, None, scenes)
            else:
                joint = joint.view(n, b, -1)
                if keep is None:  # no episode ends inside: one fused call over the whole sequences
                    outputs = self.net.recur_sequence(joint, hidden)
                else:
                    # the cell step by step, the state zeroed where an episode ended. (One fused call
                    # over the episodes' segments was slower, measured: early in a run with the start
                    # curriculum a 20-step rollout of 140 agents holds some 400 short segments.)
                    # unbind, not joint[t]: each select's backward would write a zeroed copy of the
                    # whole (T, B, J) tensor (a fifth of an update's time at widths 256)
                    outputs = []
                    for t, step in enumerate(joint.unbind(0)):
                        hidden = self.net.lstm(step, hidden)
                        outputs.append(hidden[0])
                        hidden = keep_rows(hidden, keep[t])
                    outputs = torch.stack(outputs)
                logits, values = self.net.heads(outputs)
        return logits.float().view(n, b, -1), values.float().view(n, b)

    def unroll_sequences(self, space: StateSpace, states, goals, lengths, hidden, graph):
        """The LSTM network over N sequences of different lengths, for learning: states and goals (L, N)
        padded after each sequence's `lengths` (N,) steps, the LSTM state (h, c) (N, lstm) before their
        first step. Every layer runs on the real steps only, packed as torch packs sequences
        (`ActorCritic.recur_packed`); the padding's logits and values are 0. -> logits (L, N, 10),
        values (L, N). (Padded to the longest, a TSE batch is some three quarters padding, measured.)"""
        length, n = states.shape
        order, batch_sizes, (step, seq) = packed_order(lengths)
        view, target, target_rows, r_t, r_g = self.inputs(space, states[step, seq], goals[step, seq])
        h, c = hidden
        sorted_rows = self.tensor(order)
        with self.autocast():
            joint, _ = self.net.encode(view, target, r_t, r_g, graph, target_rows)
            outputs = self.net.recur_packed(
                joint,
                torch.from_numpy(batch_sizes),
                (h[sorted_rows[: batch_sizes[0]]], c[sorted_rows[: batch_sizes[0]]]),
            )
            logits, values = self.net.heads(outputs)
        where = (self.tensor(step), self.tensor(seq))
        logits = logits.float().new_zeros(length, n, logits.shape[-1]).index_put(where, logits.float())
        values = values.float().new_zeros(length, n).index_put(where, values.float())
        return logits, values


def packed_order(lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How torch packs sequences of these lengths (N,): the order of the sequences (longest first,
    ties in their order), the batch size at each step, and each packed row's (step, sequence)."""
    lengths = np.asarray(lengths, np.int64)
    if not len(lengths) or lengths.max() < 1:
        raise ValueError("packed sequences need at least one step")
    order = np.argsort(-lengths, kind="stable")
    live = np.arange(int(lengths.max()))[:, None] < lengths[order][None]  # (L, N) sorted
    steps, ranks = np.nonzero(live)  # time-major, the sequences in sorted order within a step
    return order, live.sum(1).astype(np.int64), np.stack([steps, order[ranks]])


def run_episodes(model: Model, space: StateSpace, targets, starts, cap: int, seed: int, scene=None):
    """Run fixed episodes (target rows, start states) to the end with the model's sampled actions;
    returns SR and SPL in percent and the frames taken. FF needs `scene`, each episode's
    training-kitchen index: its scene-specific layers exist for its training kitchens only."""
    n = len(targets)
    if model.config.arch == "ff" and scene is None:
        raise ValueError("FF's episodes need their training kitchens' scene indices")
    nav = Navigators(space, space.target_kitchen[targets])
    nav.begin(np.arange(n), targets, starts, cap)
    generator = torch.Generator(model.device).manual_seed(seed)
    hidden = model.net.initial_state(n, model.device)
    ff = model.config.arch == "ff"
    history = np.repeat(starts[:, None], model.config.history, 1) if ff else None
    scene = np.asarray(scene, np.int64) if ff else None
    live = np.ones(n, bool)
    frames = 0
    with torch.no_grad():
        graph = model.graph()
        while live.any():
            idx = np.flatnonzero(live)
            goals = space.destination[nav.target[idx]]
            logits, _, rows, _ = model(
                space,
                nav.state[idx],
                goals,
                rows_of(hidden, idx),
                graph,
                scene[idx] if ff else None,
                history[idx] if ff else None,
            )
            action = torch.multinomial(F.softmax(logits, -1), 1, generator=generator).squeeze(1).cpu().numpy()
            if hidden is not None:
                for h, r in zip(hidden, rows):
                    h[idx] = r
            _, terminated, truncated = nav.step(action, idx)
            if ff:
                history[idx] = np.concatenate([history[idx, 1:], nav.state[idx, None]], 1)
            live[idx[terminated | truncated]] = False
            frames += len(idx)
    shortest = space.dist[targets, starts]
    spl = nav.success * shortest / np.maximum(np.maximum(nav.path, shortest), 1)
    return float(100.0 * nav.success.mean()), float(100.0 * spl.mean()), frames
