"""Stage 17 — stacking: a row's seeds trained in one process (`kgnavbench train --seeds 0,1,2`).

At the paper preset's 140 agents a learner is bound by the number of small operations per frame, not
by arithmetic (docs/speed.md). S seeds of one row run the same network shapes on the same kitchens, so
one process can run them as one network with a leading seed dimension: every layer is one batched
product over the S seeds' weights (`torch.baddbmm`), every elementwise operation runs once on S times
the rows. Each seed keeps its own `ActorCritic` (its parameters, optimiser, gradient clipping,
generators, agents, validation, checkpoints and run directory: kgnavbench/train.py); the stacked
weights are `torch.stack` of the seeds' own parameters, made once per pass, so the backward pass
hands each seed's gradient to its own module.

What is stacked: the acting forward passes (`collect`: the seeds' agents in lock-step, `Actors.step`) and the
learning pass over the rollouts (`unroll`), the network's parts the profile names (acting forward,
update forward, backward: 80-85% of a run). What is not: the knowledge graph's GCN (once per update
per seed, `Model.graph`), IL's and TSE's sequence passes (each seed's own, packed to different
lengths), the rare forward passes of time-limited agents, validation.

The LSTM here is the cell's formula with batched products, not torch's fused LSTM kernel (one per
weight set): a stacked seed's floats are not those of a single-seed run, so it is a run of its own
name (`runs.run_record`'s "stacked_seeds"). `tests/test_stacking.py` checks each seed's first update
against its single-seed one.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import torch
import torch.nn.functional as F
from torch import Tensor

from .agent import Model
from .models import GraphTerms, ModelConfig, ModelError, masked_softmax
from .rollout import PassInputs, Rollout, answer

Weights = dict[str, Tensor]


def check_stackable(config: ModelConfig, bf16: bool) -> None:
    """ModelError naming what a stacked run cannot train: the LSTM networks over cached features, with
    no graph, the graph's control row's detections, or the accumulated graph's "nodes" readout (every
    learned row of Table I but FF A3C)."""
    problems = []
    if config.arch != "lstm":
        problems.append(f"arch={config.arch!r} (FF A3C's scene-specific heads)")
    if config.pixels:
        problems.append("pixels=true (the encoder inside the model)")
    if config.kg != "none" and (config.kg_graph != "accumulated" or config.kg_readout != "nodes"):
        problems.append(f"kg_graph={config.kg_graph!r} with kg_readout={config.kg_readout!r}")
    if bf16:
        problems.append("bf16=true")
    if problems:
        raise ModelError(
            "seeds stack for the LSTM rows over cached features (the graph's accumulated 'nodes' "
            f"readout, or no graph) in fp32; not with {', '.join(problems)}: train such seeds one by one"
        )


def seed_progress(run):
    """`run` (a `runs.Run`) with each progress line begun by its seed, "seed 1: ...": a stacked job's
    seeds print their progress, validation and "finished" lines to one stream, interleaved."""
    say = run.progress
    return dataclasses.replace(run, progress=lambda line: say(f"seed {run.seed}: {line}"))


def parameter_names(config: ModelConfig) -> list[str]:
    """The parameters the stacked passes read (the GCN's are read by each seed's own graph terms)."""
    names = ["siamese", "fusion", "heads_hidden", "policy", "value"]
    names = [f"{layer}.{p}" for layer in names for p in ("weight", "bias")]
    names += ["lstm.weight_ih", "lstm.weight_hh", "lstm.bias_ih", "lstm.bias_hh"]
    if config.detections:
        names += ["detections.weight", "detections.bias"]
    if config.kg == "attention":
        names += ["kg.score.weight", "kg.score.bias"]
        if config.attention_context:
            names.append("kg.score_context.weight")
    return names


def stacked_weights(models: list[Model]) -> Weights:
    """Each stacked parameter (S, ...) from the seeds' own: autograd hands each seed its gradient."""
    own = [dict(m.net.named_parameters()) for m in models]
    return {name: torch.stack([p[name] for p in own]) for name in parameter_names(models[0].config)}


def stacked_readout(graphs: list[GraphTerms | None]) -> tuple[Tensor, Tensor, Tensor] | None:
    """The seeds' "nodes" readout terms (`GraphTerms.readout`) stacked: (S, ...) each."""
    if graphs[0] is None:
        return None
    return tuple(torch.stack(parts) for parts in zip(*(g.readout for g in graphs)))


def for_acting(weights: Weights, readout):
    """The weights and readout terms without autograd, for acting."""
    w = {k: v.detach() for k, v in weights.items()}
    return w, None if readout is None else tuple(t.detach() for t in readout)


def linear(x: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """The S seeds' linear layers at once: x (S, ..., in), weight (S, out, in), bias (S, out)."""
    lead = x.shape[:-1]
    x = x.reshape(x.shape[0], -1, x.shape[-1])
    wt = weight.transpose(1, 2)
    y = torch.bmm(x, wt) if bias is None else torch.baddbmm(bias.unsqueeze(1), x, wt)
    return y.reshape(*lead, -1)


# ------------------------------------------------------------------------------------------------
# The network with a seed dimension: `ActorCritic.encode`, its LSTM cell and heads, S at once


def encode(config: ModelConfig, w: Weights, readout, view, target, target_rows, r_t, r_g) -> Tensor:
    """`ActorCritic.encode` of S seeds: view (S, N, F), each seed's distinct targets (S, G, F) and every
    row's (S, N), the visible types (S, N, 125) -> the LSTM's input (S, N, J)."""
    h = config.hidden
    s_t = F.relu(linear(view.float(), w["siamese.weight"], w["siamese.bias"]))
    s_g = F.relu(linear(target.float(), w["siamese.weight"], w["siamese.bias"]))
    fusion = w["fusion.weight"]
    per_target = linear(s_g, fusion[:, :, h:], w["fusion.bias"])  # the target's half once per target
    rows = per_target.gather(1, target_rows.unsqueeze(-1).expand(-1, -1, per_target.shape[-1]))
    joint = F.relu(linear(s_t, fusion[:, :, :h]) + rows)
    if config.kg != "none":
        r_t, r_g = (r_t > 0).float(), (r_g > 0).float()
        return torch.cat([joint, node_readout(config, w, readout, r_t, r_g, joint)], -1)
    if config.detections:
        r = (torch.cat([r_t, r_g], -1) > 0).float()
        return torch.cat([joint, F.relu(linear(r, w["detections.weight"], w["detections.bias"]))], -1)
    return joint


def node_readout(
    config: ModelConfig, w: Weights, readout, r_t: Tensor, r_g: Tensor, context: Tensor
) -> Tensor:
    """`KnowledgeGraph.node_readout_of` of S seeds: (S, N, 125) each -> (S, N, width); the attention's
    scores computed for the R_z nodes only, as there."""
    r_z = torch.maximum(r_t, r_g)
    first, e1, e2 = readout
    if config.kg != "attention":  # +KG: u . Q_i + b per R_z node
        return r_z * first[:, None, None] + r_t * e1[:, None] + r_g * e2[:, None]
    s, b, n = r_z.shape
    seeds, rows, nodes = r_z.nonzero(as_tuple=True)  # seed-major: each seed's nodes together
    kinds = torch.cat([first[:, None] + e1, first[:, None] + e2, first[:, None] + e1 + e2], 1)
    kind = (r_t[seeds, rows, nodes] + 2 * r_g[seeds, rows, nodes] - 1).long()
    pre = kinds.reshape(-1, kinds.shape[-1]).index_select(0, seeds * 3 * n + kind * n + nodes)
    if config.attention_context:
        by_row = linear(context, w["kg.score_context.weight"])
        pre = pre + by_row.reshape(-1, by_row.shape[-1]).index_select(0, seeds * b + rows)
    counts = torch.bincount(seeds, minlength=s).tolist()
    picked = torch.cat(
        [
            F.linear(F.relu(part), w["kg.score.weight"][i], w["kg.score.bias"][i])
            for i, part in enumerate(pre.split(counts))
        ]
    )  # (nnz, softmaxes): one small product per seed
    if config.attention_bound:
        picked = config.attention_bound * torch.tanh(picked / config.attention_bound)
    k = config.softmaxes()
    scores = torch.zeros(s, b, n, k, dtype=picked.dtype, device=picked.device)
    scores = scores.index_put((seeds, rows, nodes), picked).transpose(2, 3)  # (S, N, softmaxes, 125)
    if config.attention_over == "each":
        heads = config.attention_heads
        mask = torch.cat(
            [r_t[:, :, None].expand(-1, -1, heads, -1), r_g[:, :, None].expand(-1, -1, heads, -1)], 2
        )
    else:
        mask = r_z[:, :, None]
    weights = masked_softmax(scores, mask)
    return weights[:, :, 0] if k == 1 else weights.reshape(s, b, k * n)


def lstm_input(w: Weights, joint: Tensor) -> Tensor:
    """The LSTM gates' input half, W_ih x + b_ih + b_hh, for all rows at once: (S, ..., 4 lstm)."""
    return linear(joint, w["lstm.weight_ih"], w["lstm.bias_ih"] + w["lstm.bias_hh"])


def lstm_cell(w: Weights, gates_in: Tensor, state: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """One step of S seeds' LSTM cells (torch's LSTMCell formula, gates i, f, g, o): (S, B, lstm) each."""
    h, c = state
    gates = torch.baddbmm(gates_in, h, w["lstm.weight_hh"].transpose(1, 2))
    i, f, g, o = gates.chunk(4, -1)
    c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c), c


def heads(config: ModelConfig, w: Weights, h: Tensor) -> tuple[Tensor, Tensor]:
    """`ActorCritic.heads` of S seeds: logits (S, ..., 10), values (S, ...)."""
    hidden = F.relu(linear(h, w["heads_hidden.weight"], w["heads_hidden.bias"]))
    k = config.head
    policy = linear(hidden[..., :k], w["policy.weight"], w["policy.bias"])
    return policy, linear(hidden[..., k:], w["value.weight"], w["value.bias"]).squeeze(-1)


def stacked_inputs(models: list[Model], spaces, states, goals):
    """Each seed's `Model.inputs`, stacked: the seeds' distinct targets padded to the most any has."""
    parts = [m.inputs(sp, s, g) for m, sp, s, g in zip(models, spaces, states, goals)]
    most = max(p[1].shape[0] for p in parts)
    targets = [F.pad(p[1], (0, 0, 0, most - p[1].shape[0])) for p in parts]
    view, rows, r_t, r_g = (torch.stack([p[i] for p in parts]) for i in (0, 2, 3, 4))
    return view, torch.stack(targets), rows, r_t, r_g


def state_of(models: list[Model], hidden: list, rows: int) -> tuple[Tensor, Tensor]:
    """The seeds' LSTM states (h, c) stacked, zeros where a seed has none yet."""
    states = [h if h is not None else models[0].net.initial_state(rows, models[0].device) for h in hidden]
    return torch.stack([h for h, _ in states]), torch.stack([c for _, c in states])


def forward(models: list[Model], w: Weights, readout, inputs: list[PassInputs]) -> list[tuple]:
    """The seeds' acting forward passes as one: each seed's answer (logits, value, hidden, extras)."""
    spaces, states, goals = [x.space for x in inputs], [x.states for x in inputs], [x.goals for x in inputs]
    hidden = [x.hidden for x in inputs]
    config = models[0].config
    joint = encode(config, w, readout, *stacked_inputs(models, spaces, states, goals))
    h, c = lstm_cell(w, lstm_input(w, joint), state_of(models, hidden, joint.shape[1]))
    logits, values = heads(config, w, h)
    return [(logits[i], values[i], (h[i], c[i]), {}) for i in range(len(models))]


def collect(
    actors: list, models: list[Model], graphs: list, w: Weights, readout, acting: list
) -> list[Rollout]:
    """The seeds' rollouts, their agents stepping in lock-step: `Actors.collect`'s loop with every
    step's forward pass stacked; the agents a time limit cut are answered by their own seed's model
    (a few per rollout). `acting`: each seed's (reach, stats, per_target), as `Actors.collect` takes them."""
    stacked = partial(forward, models, w, readout)
    steps = {a.opts.n_steps for a in actors}
    if len(steps) != 1:  # the seeds step in lock-step: every rollout must be as long
        raise RuntimeError(f"stacked seeds' rollouts of different lengths: {sorted(steps)} steps")
    with torch.no_grad():
        rollouts = [a.start_rollout() for a in actors]
        for t in range(steps.pop()):
            answers = stacked([a.step_inputs() for a in actors])
            for actor, model, graph, rollout, answered, args in zip(
                actors, models, graphs, rollouts, answers, acting
            ):
                logits, value, hidden, _ = answered
                cut = actor.step(rollout, t, logits, value, hidden, *args)
                if cut is not None:
                    actor.add_cut_value(rollout, t, cut, answer(model, cut.inputs, graph)[1])
        bootstraps = stacked([a.step_inputs() for a in actors])
        return [a.end_rollout(r, b[1]) for a, r, b in zip(actors, rollouts, bootstraps)]


def unroll(models: list[Model], spaces, rollouts: list[Rollout], w: Weights, readout) -> list[tuple]:
    """`Model.unroll` of S seeds' rollouts, with autograd: each seed's logits (T, B, 10), values (T, B)."""
    n, b = rollouts[0].states.shape
    states = [r.states.reshape(-1) for r in rollouts]
    goals = [sp.destination[r.targets].reshape(-1) for sp, r in zip(spaces, rollouts)]
    config = models[0].config
    joint = encode(config, w, readout, *stacked_inputs(models, spaces, states, goals))
    gates_in = lstm_input(w, joint).view(len(models), n, b, -1)
    keep = torch.stack([models[0].tensor(1.0 - r.dones) for r in rollouts])  # (S, T, B)
    state = state_of(models, [r.start_hidden for r in rollouts], b)
    outputs = []
    # unbind, not [:, t]: each select's backward would write a zeroed copy of the whole input
    for step, kept in zip(gates_in.unbind(1), keep.unbind(1)):
        state = lstm_cell(w, step, state)
        outputs.append(state[0])
        state = tuple(x * kept[..., None] for x in state)
    logits, values = heads(config, w, torch.stack(outputs, 1))
    return [(logits[i].float(), values[i].float()) for i in range(len(models))]
