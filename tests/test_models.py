"""The models stage: GCN normalisation, masked attention, the closed-form knowledge-graph branch against a
literal per-sample implementation, every network's shapes, the co-visibility graph, the committed
encoder and the per-state feature cache."""

import math
import os

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from kgnavbench import encoder, models
from kgnavbench.encoder import (
    ENCODER_FILE,
    FEATURE_DIM,
    Encoder,
    EncoderError,
    ViewSet,
    evaluate_encoder,
    load_encoder,
    state_features,
)
from kgnavbench.graph import state_graph
from kgnavbench.models import (
    CoVisibility,
    ModelConfig,
    ModelError,
    make_model,
    masked_softmax,
    normalized_adjacency,
)

N_TYPES = 125
ALL_CONFIGS = [
    (arch, kg, graph)
    for arch in ("lstm", "ff")
    for kg in ("none", "mean", "attention")
    for graph in ("accumulated", "per_step")
]


def random_objects(b: int, p: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(b, N_TYPES, generator=g) < p).to(torch.uint8)


def random_adjacency(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    a = (torch.rand(N_TYPES, N_TYPES, generator=g) < 0.08).float()
    a = torch.maximum(a, a.T)
    a.fill_diagonal_(0)
    return a


def inputs(cfg: ModelConfig, b: int = 6, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    if cfg.pixels:
        shape = (b, cfg.history, 84, 84, 3) if cfg.arch == "ff" else (b, 84, 84, 3)
        view = torch.randint(0, 256, shape, dtype=torch.uint8, generator=g)
        target = torch.randint(0, 256, (b, 84, 84, 3), dtype=torch.uint8, generator=g)
    else:
        shape = (b, cfg.history, FEATURE_DIM) if cfg.arch == "ff" else (b, FEATURE_DIM)
        view = torch.rand(shape, generator=g).half()  # the cache's dtype
        target = torch.rand(b, FEATURE_DIM, generator=g).half()
    view_objects, target_objects = random_objects(b, 0.04, seed + 1), random_objects(b, 0.04, seed + 2)
    view_objects[0] = 0  # a sample that sees nothing, with a target that shows nothing either
    target_objects[0] = 0
    target_objects[1] = view_objects[1]  # one where both show the same types
    return dict(
        view=view,
        target=target,
        view_objects=view_objects,
        target_objects=target_objects,
        graph=random_adjacency(seed) if cfg.kg_graph == "accumulated" else None,
        scene=torch.arange(b) % cfg.n_scenes,
    )


# ------------------------------------------------------------------------------------------------
# GCN normalisation and masked softmax


def test_normalized_adjacency_of_a_hand_made_path_graph():
    # 0 - 1 - 2: A + I has degrees 2, 3, 2
    a = torch.tensor([[0.0, 1, 0], [1, 0, 1], [0, 1, 0]])
    r6 = 6**-0.5
    expected = torch.tensor([[1 / 2, r6, 0], [r6, 1 / 3, r6], [0, r6, 1 / 2]])
    assert torch.allclose(normalized_adjacency(a), expected, atol=1e-7)
    # batched: the same per graph; an empty graph is the identity
    batch = torch.stack([a, torch.zeros(3, 3)])
    out = normalized_adjacency(batch)
    assert torch.allclose(out[0], expected, atol=1e-7)
    assert torch.equal(out[1], torch.eye(3))


def test_masked_softmax_is_zero_outside_the_mask_and_safe_on_an_empty_mask():
    scores = torch.tensor(
        [[1.0, 2.0, 3.0, 100.0], [5.0, -1.0, 0.0, 2.0], [1.0, 1.0, 1.0, 1.0]], requires_grad=True
    )
    mask = torch.tensor([[1, 1, 1, 0], [0, 0, 0, 0], [0, 1, 0, 0]])
    w = masked_softmax(scores, mask)
    assert torch.allclose(w[0, :3], torch.softmax(torch.tensor([1.0, 2.0, 3.0]), 0))
    assert w[0, 3] == 0
    assert torch.equal(w[1], torch.zeros(4))
    assert torch.equal(w[2], torch.tensor([0.0, 1.0, 0.0, 0.0]))
    (w * torch.arange(4.0)).sum().backward()
    assert torch.isfinite(scores.grad).all()
    assert torch.equal(scores.grad[1], torch.zeros(4))
    assert scores.grad[0, 3] == 0


# ------------------------------------------------------------------------------------------------
# The knowledge-graph branch against a literal implementation of DESIGN.md's equations


def literal_kg(
    kg: models.KnowledgeGraph, r_t, r_g, adjacency, per_step: bool, attention: bool, all_nodes: bool = False
):
    """Per sample: the graph (accumulated, or the clique over R_z), Â, H(0) = I and 3 GCN layers,
    H_t = R_t * H, H_g = R_g * H, Q = W'_f [ReLU(W'_s H_t), ReLU(W'_s H_g)], then the mean or the
    masked attention over R_z (or, all_nodes, the softmax over all 125 nodes)."""
    b, n = r_t.shape
    r_z = torch.maximum(r_t, r_g)
    pooled, weights = [], []
    for i in range(b):
        if per_step:
            a = torch.outer(r_z[i], r_z[i])
            a.fill_diagonal_(0)
        else:
            a = adjacency
        a_hat = normalized_adjacency(a)
        h = torch.eye(n)
        for w in (kg.w0, kg.w1, kg.w2):
            h = F.relu(a_hat @ h @ w)
        h_t, h_g = r_t[i][:, None] * h, r_g[i][:, None] * h
        q = kg.spatial_fusion(
            torch.cat([F.relu(kg.spatial_siamese(h_t)), F.relu(kg.spatial_siamese(h_g))], 1)
        )
        if attention:
            scores = kg.score(F.relu(kg.score_hidden(q))).squeeze(-1)
            masked = masked_softmax(scores[None], r_z[i][None])[0]
            alpha = torch.softmax(scores, 0) if all_nodes else masked
        else:
            alpha = r_z[i] / r_z[i].sum().clamp_min(1)
        pooled.append(alpha @ q)
        weights.append(alpha)
    return torch.stack(pooled), torch.stack(weights)


@pytest.mark.parametrize("graph", ["accumulated", "per_step"])
@pytest.mark.parametrize("kg", ["mean", "attention", "attention over all nodes"])
def test_closed_form_kg_branch_equals_the_literal_equations(kg, graph):
    torch.manual_seed(0)
    all_nodes = kg == "attention over all nodes"
    kg = "attention" if all_nodes else kg
    cfg = ModelConfig(kg=kg, kg_graph=graph, attention_nodes="all" if all_nodes else "visible")
    branch = make_model(cfg).kg
    # nonzero biases, so that rows outside R_t or R_g (ReLU(W'_s 0 + b) = ReLU(b)) matter
    with torch.no_grad():
        for p in branch.parameters():
            if p.dim() == 1:
                p.uniform_(-0.5, 0.5)
    x = inputs(cfg, b=8, seed=3)
    r_t, r_g = x["view_objects"].float(), x["target_objects"].float()
    fast, attention, node_features = branch(r_t, r_g, x["graph"])
    slow, alpha = literal_kg(branch, r_t, r_g, x["graph"], graph == "per_step", kg == "attention", all_nodes)
    assert torch.allclose(fast, slow, atol=1e-5, rtol=1e-4)
    if kg == "attention":
        assert torch.allclose(attention, alpha, atol=1e-6)
    else:
        assert attention is None
    assert (node_features is None) == (graph == "per_step")
    if all_nodes:  # every node has weight; those outside R_z share one
        assert torch.allclose(attention.sum(1), torch.ones(8), atol=1e-5)
        outside = ~((r_t > 0) | (r_g > 0))
        for i in range(8):
            w = attention[i][outside[i]]
            assert torch.allclose(w, w[0].expand_as(w), atol=1e-7)
    else:  # nothing in view or target: nothing pooled
        assert torch.equal(fast[0], torch.zeros_like(fast[0]))


def literal_nodes_readout(kg: models.KnowledgeGraph, r_t, r_g, adjacency, context):
    """kg_readout "nodes", per sample and node, as docs/models.md writes it: Q_i as in literal_kg;
    +KG: u . Q_i + b on the R_z nodes, 0 elsewhere; +KG+Attention: H_a = the softmax over R_z of
    w2 . ReLU(W1 Q_i + W_c I_t + b1) + b2, 0 elsewhere."""
    b, n = r_t.shape
    r_z = torch.maximum(r_t, r_g)
    h = torch.eye(n)
    for w in (kg.w0, kg.w1, kg.w2):
        h = normalized_adjacency(adjacency) @ h @ w
        if kg.norm is models.pair_norm:  # centred over the nodes, mean squared row norm 1
            h = (h - h.mean(0)) / ((h - h.mean(0)).square().sum(1).mean() + 1e-6).sqrt()
        h = F.relu(h)
    out = []
    for i in range(b):
        q = kg.spatial_fusion(
            torch.cat(
                [
                    F.relu(kg.spatial_siamese(r_t[i][:, None] * h)),
                    F.relu(kg.spatial_siamese(r_g[i][:, None] * h)),
                ],
                1,
            )
        )
        row = torch.zeros(n)
        if kg.attention:
            pre = kg.score_hidden(q) + (kg.score_context(context[i]) if hasattr(kg, "score_context") else 0)
            scores = kg.score(F.relu(pre))  # (125, heads)
            if kg.bound:
                scores = kg.bound * torch.tanh(scores / kg.bound)
            masks = [r_t[i] > 0] * kg.heads + [r_g[i] > 0] * kg.heads if kg.each else [r_z[i] > 0] * kg.heads
            row = torch.zeros(len(masks), n)
            for head, keep in enumerate(masks):
                if keep.any():
                    row[head, keep] = torch.softmax(scores[keep, head], 0)
            row = row.reshape(-1)
        else:
            row = r_z[i] * kg.node_readout(q).squeeze(-1)
        out.append(row)
    return torch.stack(out)


@pytest.mark.parametrize(
    "kg",
    [
        "mean",
        "attention",
        "attention on Q alone",
        "attention, 3 heads, PairNorm",
        "attention over each image",
        "attention, bounded scores",
    ],
)
@pytest.mark.parametrize("edges", ["binary", "ppmi"])
def test_nodes_readout_equals_the_literal_equations(kg, edges):
    torch.manual_seed(0)
    q_alone, each = kg == "attention on Q alone", kg == "attention over each image"
    cfg = ModelConfig(
        kg="mean" if kg == "mean" else "attention",
        kg_readout="nodes",
        kg_edges=edges,
        attention_context=not q_alone,
        attention_heads=3 if "heads" in kg else 1,
        gcn_norm="pair" if "PairNorm" in kg else "none",
        attention_over="each" if each else "union",
        attention_bound=1.5 if "bounded" in kg else 0.0,
    )
    heads = cfg.softmaxes()
    kg = cfg.kg
    model = make_model(cfg)
    with torch.no_grad():  # nonzero biases; larger weights, so that the nodes' scores differ
        for p in model.kg.parameters():
            p.uniform_(-0.5, 0.5) if p.dim() == 1 else p.mul_(3)
    x = inputs(cfg, b=8, seed=3)
    r_t, r_g = x["view_objects"].float(), x["target_objects"].float()
    context = torch.randn(8, cfg.hidden)
    adjacency = x["graph"] if edges == "binary" else x["graph"] * (1 + torch.rand(N_TYPES, N_TYPES)).triu(1)
    adjacency = torch.maximum(adjacency, adjacency.T)  # weighted, symmetric
    fast, attention, node_features = model.kg(r_t, r_g, adjacency, context=context)
    slow = literal_nodes_readout(model.kg, r_t, r_g, adjacency, context)
    assert fast.shape == (8, N_TYPES * heads) and node_features.shape == (N_TYPES, cfg.gcn)
    assert torch.allclose(fast, slow, atol=1e-5, rtol=1e-4)
    r_z = (r_t > 0) | (r_g > 0)
    per_head = fast.view(8, heads, N_TYPES)
    masks = torch.stack([r_t > 0, r_g > 0], 1) if each else r_z[:, None, :].expand_as(per_head)
    assert torch.equal(per_head[~masks], torch.zeros_like(per_head[~masks]))  # one slot per object
    if kg == "attention":
        assert torch.allclose(attention, per_head.mean(1))  # what recordings show: the softmaxes' mean
        sums = per_head.sum(2)
        assert torch.allclose(sums, masks.any(2).float(), atol=1e-5) and fast[0].sum() == 0
        fast = attention
        if cfg.attention_bound:  # no weight more than e^(2b) times another of its softmax
            for row, keep in zip(per_head.reshape(-1, N_TYPES), masks.reshape(-1, N_TYPES)):
                if keep.any():
                    assert row[keep].max() <= row[keep].min() * math.exp(2 * cfg.attention_bound) * 1.0001
        # the scores see the view (or not): another I_t gives other weights over the same objects
        _, other, _ = model.kg(r_t, r_g, adjacency, context=context + torch.randn(8, cfg.hidden))
        assert torch.allclose(other[1:], fast[1:], atol=1e-4) == q_alone
    else:
        assert attention is None
    # the whole network: the LSTM reads [I_t, the readout], 256 + 125 wide, and every weight learns
    logits, value, _, extras = model(**x, state=None)
    assert model.lstm.input_size == cfg.hidden + N_TYPES * heads
    (logits.square().sum() + value.sum()).backward()
    assert all(p.grad is not None for p in model.parameters())
    graph = model.graph_terms(x["graph"])
    assert torch.equal(model(**{**x, "graph": graph}, state=None)[0], logits)


def test_nodes_readout_takes_the_accumulated_graph_and_visible_nodes():
    with pytest.raises(ModelError, match="kg_graph='accumulated'"):
        make_model(ModelConfig(kg="mean", kg_readout="nodes", kg_graph="per_step"))
    with pytest.raises(ModelError, match="attention_nodes='visible'"):
        make_model(ModelConfig(kg="attention", kg_readout="nodes", attention_nodes="all"))
    with pytest.raises(ModelError, match="attention_heads"):
        make_model(ModelConfig(kg="attention", attention_heads=2))  # pooled: one softmax
    for field, value in [("kg_readout", "sum"), ("kg_edges", "pmi"), ("gcn_norm", "batch")]:
        with pytest.raises(ModelError, match=f"ModelConfig.{field}"):
            make_model(ModelConfig(kg="mean", **{field: value}))


@pytest.mark.parametrize("kg", ["mean", "attention"])
def test_graph_terms_computed_once_equal_the_per_step_computation(kg):
    # the trainer computes the accumulated graph's terms once per update and shares them across the
    # rollout's steps: outputs and gradients must be those of recomputing them at every step
    torch.manual_seed(0)
    cfg = ModelConfig(kg=kg)
    model = make_model(cfg)
    steps = [inputs(cfg, b=6, seed=s) for s in (1, 2, 3)]
    adjacency = steps[0]["graph"]
    results = []
    for shared in (False, True):
        model.zero_grad()
        graph = model.graph_terms(adjacency) if shared else adjacency
        assert isinstance(graph, models.GraphTerms) == shared
        outs = [model(**{**x, "graph": graph}, state=None) for x in steps]
        loss = sum(logits.square().sum() + value.sum() for logits, value, _, _ in outs)
        loss.backward()
        grads = [p.grad.clone() for p in model.kg.parameters()]
        results.append(([o[0] for o in outs], [o[3]["attention"] for o in outs], grads))
    (logits_a, att_a, grad_a), (logits_b, att_b, grad_b) = results
    assert all(torch.equal(a, b) for a, b in zip(logits_a, logits_b))
    assert all((a is None and b is None) or torch.equal(a, b) for a, b in zip(att_a, att_b))
    assert all(torch.allclose(a, b, atol=1e-6, rtol=1e-5) for a, b in zip(grad_a, grad_b))
    # without an accumulated graph there is nothing to share
    assert make_model(ModelConfig(kg="none")).graph_terms(adjacency) is adjacency
    per_step = make_model(ModelConfig(kg=kg, kg_graph="per_step"))
    assert per_step.graph_terms(adjacency) is adjacency


@pytest.mark.parametrize("graph", ["accumulated", "per_step"])
def test_attention_weights_are_zero_outside_the_visible_types(graph):
    cfg = ModelConfig(kg="attention", kg_graph=graph)
    model = make_model(cfg)
    x = inputs(cfg, b=8, seed=1)
    _, _, _, extras = model(**x, state=None)
    alpha = extras["attention"]
    r_z = (x["view_objects"] > 0) | (x["target_objects"] > 0)
    assert alpha.shape == (8, N_TYPES)
    assert torch.equal(alpha[~r_z], torch.zeros_like(alpha[~r_z]))
    assert torch.equal(alpha[0], torch.zeros(N_TYPES))  # R_z empty
    sums = alpha[1:].sum(1)
    assert torch.allclose(sums, torch.ones_like(sums), atol=1e-6)


# ------------------------------------------------------------------------------------------------
# Networks


@pytest.mark.parametrize("arch,kg,graph", ALL_CONFIGS)
def test_output_shapes_of_every_network(arch, kg, graph):
    cfg = ModelConfig(arch=arch, kg=kg, kg_graph=graph)
    model = make_model(cfg)
    x = inputs(cfg)
    logits, value, state, extras = model(**x, state=model.initial_state(6))
    assert logits.shape == (6, 10) and value.shape == (6,)
    assert torch.isfinite(logits).all() and torch.isfinite(value).all()
    if arch == "lstm":
        assert [t.shape for t in state] == [(6, 256), (6, 256)]
    else:
        assert state is None and model.initial_state(6) is None
    assert (extras["attention"] is None) == (kg != "attention")
    if kg != "none" and graph == "accumulated":
        assert extras["node_features"].shape == (N_TYPES, 128)
    else:
        assert extras["node_features"] is None
    (logits.sum() + value.sum()).backward()
    assert all(p.grad is not None for n, p in model.named_parameters() if not n.startswith("scene_"))


@pytest.mark.parametrize("kg", ["none", "attention"])
@pytest.mark.parametrize("pixels", [False, True])
def test_each_distinct_target_once_gives_the_per_row_network(kg, pixels):
    """target_rows: the siamese layer and the target's half of the fusion layer run once per distinct
    target (what a rollout's rows share); the outputs and gradients are those of one target per row."""
    cfg = ModelConfig(kg=kg, pixels=pixels)
    model = make_model(cfg)
    x = inputs(cfg, b=6)
    rows = torch.tensor([0, 1, 1, 0, 2, 1])
    distinct = x["target"][:3]
    x["target_objects"] = x["target_objects"][:3][rows]
    per_row = model(**{**x, "target": distinct[rows]}, state=None)
    once = model(**{**x, "target": distinct}, state=None, target_rows=rows)
    torch.testing.assert_close(once[0], per_row[0], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(once[1], per_row[1], rtol=1e-5, atol=1e-5)
    grads = []
    for out in (per_row, once):
        model.zero_grad()
        (out[0].square().sum() + out[1].sum()).backward()
        grads.append({n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None})
    assert grads[0].keys() == grads[1].keys()
    for name in grads[0]:
        torch.testing.assert_close(grads[1][name], grads[0][name], rtol=1e-4, atol=1e-5, msg=name)
    with pytest.raises(ModelError, match="3 targets for 6 views"):
        model(**{**x, "target": distinct}, state=None)


@pytest.mark.parametrize("arch", ["lstm", "ff"])
def test_pixel_models_take_uint8_views(arch):
    cfg = ModelConfig(arch=arch, kg="attention", pixels=True, history=2)
    model = make_model(cfg)
    logits, value, _, extras = model(**inputs(cfg, b=3), state=None)
    assert logits.shape == (3, 10) and value.shape == (3,) and extras["attention"].shape == (3, N_TYPES)


def test_bf16_autocast_forward_and_backward():
    cfg = ModelConfig(kg="attention")
    model = make_model(cfg)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        logits, value, state, _ = model(**inputs(cfg), state=None)
    assert torch.isfinite(logits.float()).all()
    (logits.float().sum() + value.float().sum()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_lstm_state_none_is_the_zero_state_and_the_state_carries_memory():
    torch.manual_seed(0)
    cfg = ModelConfig(kg="mean")
    model = make_model(cfg)
    x = inputs(cfg)
    a = model(**x, state=None)
    b = model(**x, state=model.initial_state(6))
    assert torch.equal(a[0], b[0])
    c = model(**x, state=a[2])  # the second step of the same episodes differs from a fresh start
    assert not torch.allclose(c[0], a[0])


def test_ff_scene_heads_pick_each_samples_scene():
    torch.manual_seed(0)
    cfg = ModelConfig(arch="ff", kg="attention", n_scenes=3)
    model = make_model(cfg)
    x = inputs(cfg, b=7)
    x["scene"] = torch.tensor([2, 0, 1, 2, 0, 0, 1])
    logits, value, _, _ = model(**x, state=None)
    for i in range(7):  # each sample alone gives the same answer as inside the mixed batch
        one = {k: (v[i : i + 1] if k not in ("graph",) and v is not None else v) for k, v in x.items()}
        li, vi, _, _ = model(**one, state=None)
        assert torch.allclose(li, logits[i : i + 1], atol=1e-6) and torch.allclose(
            vi, value[i : i + 1], atol=1e-6
        )
    other = dict(x, scene=(x["scene"] + 1) % 3)
    assert not torch.allclose(model(**other, state=None)[0], logits)
    with pytest.raises(ModelError, match="scene"):
        model(**dict(x, scene=torch.full((7,), 3)), state=None)
    with pytest.raises(ModelError, match="scene"):
        model(**dict(x, scene=None), state=None)


def test_make_model_names_the_bad_field():
    for field, value in [
        ("arch", "gru"),
        ("kg", "graph"),
        ("kg_graph", "daily"),
        ("lstm", 0),
        ("history", "4"),
    ]:
        with pytest.raises(ValueError, match=f"ModelConfig.{field}"):
            make_model(ModelConfig(**{field: value}))
    with pytest.raises(ModelError, match="adjacency"):
        cfg = ModelConfig(kg="mean")
        make_model(cfg)(**dict(inputs(cfg), graph=None), state=None)


def test_covisibility_counts_pairs_seen_together():
    covis = CoVisibility()
    frames = np.zeros((3, N_TYPES), np.uint8)
    frames[0, [1, 2, 3]] = 1
    frames[1, [1, 2]] = 1
    frames[2, [7]] = 1  # alone: no edge, no self loop
    covis.add(frames)
    assert covis.counts[1, 2] == 2 and covis.counts[2, 1] == 2 and covis.counts[1, 3] == 1
    assert covis.counts.diagonal().sum() == 0 and covis.counts.sum() == 2 * (2 + 1 + 1)
    a = covis.adjacency()
    assert a.dtype == torch.float32 and torch.equal(a, a.T) and a.sum() == 6 and a[7].sum() == 0
    covis.add(torch.from_numpy(frames[:1]))
    other = CoVisibility()
    other.load_state_dict(covis.state_dict())
    assert torch.equal(other.counts, covis.counts) and other.counts[1, 2] == 3
    with pytest.raises(ModelError, match="co-visibility"):
        other.load_state_dict({"counts": torch.zeros(3, 3)})


def test_covisibility_edge_weights_by_hand():
    covis = CoVisibility(n_types=4)
    counts = torch.tensor([[0, 6, 1, 0], [6, 0, 1, 0], [1, 1, 0, 2], [0, 0, 2, 0]], dtype=torch.float64)
    covis.counts = counts.clone()
    row, total = counts.sum(1), counts.sum()  # (7, 7, 4, 2), 20
    ppmi = covis.adjacency("ppmi").double()
    # 0-1: log(6 * 20 / 49) > 0; 0-2: log(1 * 20 / 28) < 0, no edge; 2-3: log(2 * 20 / 8) > 0
    assert ppmi[0, 1] == pytest.approx(math.log(6 * 20 / 49), rel=1e-6)
    assert ppmi[2, 3] == pytest.approx(math.log(2 * 20 / 8), rel=1e-6)
    assert ppmi[0, 2] == 0 and ppmi[0, 3] == 0 and torch.equal(ppmi, ppmi.T)
    assert ppmi.diagonal().sum() == 0 and row.sum() == total
    assert torch.equal(covis.adjacency("counts"), (counts / 6).float())
    assert torch.equal(covis.adjacency(), (counts > 0).float())
    assert torch.equal(CoVisibility(n_types=4).adjacency("ppmi"), torch.zeros(4, 4))  # nothing seen
    # the 5 strongest edges per node: an edge stays where it is among the 5 strongest of either end
    dense = CoVisibility(n_types=12)
    counts = torch.randint(0, 40, (12, 12), generator=torch.Generator().manual_seed(0)).double()
    dense.counts = counts + counts.T
    full, top = dense.adjacency("ppmi"), dense.adjacency("ppmi_top5")
    assert torch.equal(top, top.T) and torch.equal(top[top > 0], full[top > 0])
    strongest = full.topk(5, dim=1).indices
    for i in range(12):
        for j in range(12):
            kept = j in strongest[i].tolist() or i in strongest[j].tolist()
            assert (top[i, j] > 0) == (kept and full[i, j] > 0)
    assert (top > 0).sum() < (full > 0).sum()
    with pytest.raises(ModelError, match="edges='pmi'"):
        covis.adjacency("pmi")


# ------------------------------------------------------------------------------------------------
# The encoder and the per-state features


@pytest.fixture(scope="module")
def floorplan5():
    """A validation kitchen (never seen in pretraining), built into the hermetic cache (~8 s)."""
    return state_graph("FloorPlan5")


def test_committed_encoder_beats_a_random_one_on_a_validation_kitchen(floorplan5):
    g = floorplan5
    keep = np.linspace(0, g.n_states - 1, 512).round().astype(np.int64)
    data = ViewSet(
        np.asarray(g.views)[keep],
        np.asarray(g.object_vectors)[keep],
        np.searchsorted((-30, 0, 30, 60), g.pitch[keep]),
        (g.opened[keep] >= 0).astype(np.float32),
    )
    meta = encoder.read_encoder_file()["meta"]
    assert "FloorPlan5" not in meta["kitchens"] and "FloorPlan5" in meta["val_kitchens"]
    trained = evaluate_encoder(load_encoder(), data)
    torch.manual_seed(0)
    random = evaluate_encoder(Encoder(), data)
    assert trained["mAP"] > random["mAP"] + 0.2, (trained, random)
    assert trained["micro_f1"] > random["micro_f1"] + 0.2, (trained, random)


def test_encoder_file_errors_name_the_file(tmp_path):
    with pytest.raises(EncoderError, match="missing.pt.*missing"):
        load_encoder(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(EncoderError, match="bad.pt.*corrupt"):
        load_encoder(bad)


def test_saved_encoder_round_trips_in_fp16(tmp_path):
    torch.manual_seed(1)
    net = Encoder()
    path = tmp_path / "enc.pt"
    encoder.save_encoder(net, path, {"seed": 1})
    loaded = load_encoder(path)
    for (k, a), b in zip(net.state_dict().items(), loaded.state_dict().values()):
        assert torch.equal(a.half().float(), b), k
    assert encoder.read_encoder_file(path)["meta"] == {"seed": 1}
    assert len(encoder.encoder_hash(path)) == 12


def test_pretraining_is_deterministic(floorplan5, floorplan1_tasks):
    args = dict(
        kitchens=["FloorPlan5"], val_kitchens=["FloorPlan5"], epochs=1, samples_per_epoch=64, batch_size=32
    )
    with pytest.raises(EncoderError, match="overlap"):
        encoder.pretrain_encoder(out=None, log=lambda *_: None, **args)
    args.update(val_kitchens=["FloorPlan1"], max_val_views=64)
    a, meta_a = encoder.pretrain_encoder(out=None, seed=3, log=lambda *_: None, **args)
    b, meta_b = encoder.pretrain_encoder(out=None, seed=3, log=lambda *_: None, **args)
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))
    assert meta_a == meta_b and meta_a["images"] == 64 and meta_a["val"]["views"] == 64


def test_state_features_are_cached_reused_and_rebuilt(floorplan5, monkeypatch, capsys):
    features = state_features("FloorPlan5")
    assert features.shape == (floorplan5.n_states, FEATURE_DIM) and features.dtype == np.float16
    assert np.isfinite(features).all() and (features >= 0).all()
    path = encoder.features_path("FloorPlan5")
    assert path.exists() and path.name.endswith(f".features-{encoder.encoder_hash()}.npy")
    # the same numbers as encoding the views now
    some = np.array(floorplan5.views[:16])  # a writable copy of the memory-mapped views
    with torch.no_grad():
        direct = load_encoder()(torch.from_numpy(some)).half().numpy()
    assert np.allclose(features[:16].astype(np.float32), direct.astype(np.float32), atol=1e-2, rtol=1e-2)

    # the second call reads the file: no encoder is needed
    def no_encoder():
        raise AssertionError("the encoder ran again")

    monkeypatch.setattr(encoder, "_cached_encoder", no_encoder)
    again = state_features("FloorPlan5")
    assert isinstance(again, np.memmap) and np.array_equal(again, features)
    monkeypatch.undo()
    # (the cache is only ever replaced by a rename; the test overwrites it in place, so it lets go of the
    # memory maps first: reading a truncated mapping is a bus error)
    features = np.array(features)
    del again

    # a corrupt file is rebuilt, with a notice on stderr
    mtime = path.stat().st_mtime_ns
    path.write_bytes(b"garbage")
    rebuilt = state_features("FloorPlan5")
    # to the encoder's float16 tolerance, not bytes: on an Intel Xeon with AMX the encoder's output
    # differed between the process that built the cache and this one (2026-12-07)
    assert np.allclose(rebuilt.astype(np.float32), features.astype(np.float32), atol=1e-2, rtol=1e-2)
    assert "cannot be trusted" in capsys.readouterr().err
    # a file of the wrong shape too
    np.save(path, np.zeros((3, FEATURE_DIM), np.float16))
    assert state_features("FloorPlan5").shape == (floorplan5.n_states, FEATURE_DIM)
    assert path.stat().st_mtime_ns != mtime


def test_committed_encoder_file_exists():
    assert ENCODER_FILE.exists() and os.path.getsize(ENCODER_FILE) < 8_000_000
    meta = encoder.read_encoder_file()["meta"]
    for key in ("seed", "epochs", "kitchens", "val"):
        assert key in meta
    assert len(meta["kitchens"]) == 20 and meta["val"]["mAP"] > meta["val_random_init"]["mAP"]


def test_the_graph_diagnostic_measures_the_models_own_features():
    """benchmarks/gcn_smoothing.py's layers are the model's: on shipped +KG and +KG+Attention
    checkpoints (PairNorm after each layer), its last layer is `KnowledgeGraph.node_features` exactly,
    and PairNorm is in them (without it the layers differ)."""
    import importlib.util
    from pathlib import Path

    from kgnavbench.runs import load_checkpoint

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("gcn_smoothing", root / "benchmarks" / "gcn_smoothing.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    for run in ("kg_attention-0efa248388", "kg_attention-49df282f6f"):  # +KG and +KG+Attention, seed 0
        ck = load_checkpoint(root / "zoo" / run / "best.pt")
        covis = models.CoVisibility()
        covis.load_state_dict(ck["covis"])
        net = models.make_model(models.ModelConfig(**ck["model_config"]))
        net.load_state_dict(ck["model"])
        assert net.cfg.gcn_norm == "pair"
        a_hat = models.normalized_adjacency(covis.adjacency(net.cfg.kg_edges))
        with torch.no_grad():
            ours = bench.layers(net.kg, a_hat)
            assert len(ours) == 3 and torch.equal(ours[-1], net.kg.node_features(a_hat))
            bare = F.relu(a_hat @ net.kg.w0)  # the first layer without PairNorm: not the model's
            assert not torch.allclose(ours[0], bare)
