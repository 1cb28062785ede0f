"""Stage 11 — models: the actor-critic networks of the learned methods (DESIGN.md "Learned agents"),
over the frozen encoder's per-state features (`kgnavbench.encoder`).

`ModelConfig`, `make_model` -> `ActorCritic`:
     I_t = ReLU(W_f [ReLU(W_s X_t), ReLU(W_s X_g)])                     siamese + fusion, (B, 256)
     +KG: Â = D^-1/2 (A + I) D^-1/2, H(l+1) = ReLU(Â H(l) W(l)), H(0) = I, 3 layers -> H (125, 128);
          Q_i = W'_f [ReLU(W'_s R_t,i H_i), ReLU(W'_s R_g,i H_i)]          (125, 128) per sample;
          "mean": mean of Q over R_z = R_t OR R_g; "attention": alpha = masked softmax over R_z of
          w2 . ReLU(W1 Q_i), H_a = sum alpha_i Q_i                          (B, 128)
     detections (the graph's control row, no GCN): ReLU(W_d [R_t, R_g])                (B, 128)
     lstm: LSTM([I_t, kg or detections]) (256), then policy (10 logits) and value MLPs.
     ff (Zhu et al. 2017): siamese + fusion over the last `history` frames (and the target stacked as
          many times), then a scene-specific layer and policy / value heads per training kitchen.
`CoVisibility`: the accumulated knowledge graph (co-visibility counts of the 125 types).

Why the knowledge-graph branch is cheap. R_t and R_g are 0/1, so Q_i takes one of four values per
node, all linear in (R_t,i, R_g,i): Q_i = base + R_t,i D1_i + R_g,i D2_i, with base (d,) and D1, D2
(125, d) computed once per forward from the shared graph. The mean and the attention pool are then
two (B, 125) x (125, d) products, and an attention score is one of three per-node numbers (only
nodes in R_z count). The per-step graph (the clique over R_z) is as exact and cheap: in a clique every
R_z node averages the same rows, so after any number of GCN layers all R_z rows equal one vector per
sample. `tests/test_models.py` checks both against a literal per-sample implementation.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, fields

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .encoder import FEATURE_DIM, N_TYPES, Encoder
from .errors import KgnavbenchError
from .world import ACTIONS

# oneDNN's bf16 kernels (AVX512-BF16 or AMX); see ActorCritic._lstm
_CPU_HAS_BF16 = bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())

N_ACTIONS = len(ACTIONS)


class ModelError(KgnavbenchError, ValueError):
    """Bad model input: unknown option, wrongly shaped tensors, a graph the model cannot use."""


# ------------------------------------------------------------------------------------------------
# The networks


@dataclass
class ModelConfig:
    arch: str = (
        "lstm"  # "lstm" (LSTM actor-critic) | "ff" (Zhu et al.: last `history` frames, per-scene heads)
    )
    kg: str = "none"  # "none" | "mean" (+KG: mean of Q over the R_z nodes) | "attention" (+KG+Attention)
    kg_graph: str = (
        "accumulated"  # "accumulated" (co-visibility counts, passed in) | "per_step" (clique over R_z)
    )
    feature_dim: int = FEATURE_DIM
    hidden: int = 256  # siamese and fusion width
    gcn: int = 128  # GCN width per layer; also the width of Q and of the attention's hidden layer
    lstm: int = 256
    head: int = 128  # hidden width of the policy and value MLPs
    history: int = 4  # ff only
    n_scenes: int = 20  # ff only: one scene-specific layer and policy/value heads per training kitchen
    pixels: bool = False  # end to end: the Encoder CNN inside the model, inputs are uint8 views
    # attention's softmax over "visible": the R_z nodes only (masked; our reading of the paper's
    # equations), or "all": all |V| = 125 nodes, as the paper's wording reads (a node outside R_z has
    # Q = base, the spatial features of an empty row, so those nodes share one score)
    attention_nodes: str = "visible"
    # the control row of the graph: the LSTM row gains the detections the KG rows see, R_t and R_g,
    # through one layer ReLU(W_d [R_t, R_g]) as wide as the graph's pooled Q, with no GCN (kg "none")
    detections: bool = False
    # the accumulated graph's edge weights (`CoVisibility.adjacency`): "binary" (ever seen together;
    # the first reading, whose three GCN layers collapse every node onto one direction), "ppmi"
    # (positive pointwise mutual information of the co-visibility counts) or "counts" (the counts over
    # their maximum)
    kg_edges: str = "binary"
    # what the graph hands the LSTM: "pooled" (the first reading: the mean or attention-weighted mean
    # of Q over R_z, (B, gcn)) or "nodes" (the paper's |V|-dimensional vectors: +KG one scalar of Q per
    # R_z node, +KG+Attention H_a itself, the softmax over R_z of scores conditioned on Q and on the
    # fused view and target I_t; (B, 125), zero outside R_z)
    kg_readout: str = "pooled"
    # the "nodes" readout's attention scores see the fused view and target I_t beside each node's Q
    # (false: Q alone, which depends on the view and the target through R_t and R_g only)
    attention_context: bool = True
    # the "nodes" readout's attention heads: k softmaxes over R_z, each from its own score layer w2,
    # H_a (B, k * 125) into the LSTM (1: the paper's one H_a)
    attention_heads: int = 1
    # the "nodes" readout's softmax: "union" over R_z = R_t OR R_g (the paper's "objects in the current
    # observation and target image", one H_a), or "each": one over the view's objects R_t and one over
    # the target image's R_g (as the paper's H_t and H_g are per image), H_a = [a_t, a_g] (B, 2 * 125)
    attention_over: str = "union"
    # the "nodes" attention's scores bounded to (-b, b) by b tanh(s / b), so that no softmax saturates
    # into a one-hot choice (weights differ at most e^(2b)-fold); 0: unbounded, as the paper's
    attention_bound: float = 0.0
    # after each GCN layer's propagation, before its ReLU: "none" (the paper's eq. 1) or "pair"
    # (PairNorm, Zhao and Akoglu 2020: the nodes' features centred and scaled to a mean squared row norm
    # of 1, against the over-smoothing that makes every node's row alike)
    gcn_norm: str = "none"

    def validate(self) -> None:
        choices = {
            "arch": ("lstm", "ff"),
            "kg": ("none", "mean", "attention"),
            "kg_graph": ("accumulated", "per_step"),
            "attention_nodes": ("visible", "all"),
            "kg_edges": EDGE_WEIGHTS,
            "kg_readout": ("pooled", "nodes"),
            "gcn_norm": ("none", "pair"),
            "attention_over": ("union", "each"),
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ModelError(
                    f"ModelConfig.{name}={getattr(self, name)!r}: expected one of {', '.join(allowed)}"
                )
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in (int, "int") and (
                not isinstance(value, int) or isinstance(value, bool) or value < 1
            ):
                raise ModelError(f"ModelConfig.{f.name}={value!r}: expected a positive integer")
        for name in ("pixels", "detections", "attention_context"):
            if not isinstance(getattr(self, name), bool):
                raise ModelError(f"ModelConfig.{name}={getattr(self, name)!r}: expected true or false")
        if self.detections and self.kg != "none":
            raise ModelError("ModelConfig.detections is the graph's control: it takes kg='none'")
        if self.kg_readout == "nodes" and self.kg != "none":
            if self.kg_graph != "accumulated":
                raise ModelError("ModelConfig.kg_readout='nodes' takes kg_graph='accumulated'")
            if self.kg == "attention" and self.attention_nodes != "visible":
                raise ModelError("ModelConfig.kg_readout='nodes' takes attention_nodes='visible'")
        if not isinstance(self.attention_bound, (int, float)) or not 0 <= self.attention_bound < 1e6:
            raise ModelError(f"ModelConfig.attention_bound={self.attention_bound!r}: expected a number >= 0")
        if (self.attention_heads > 1 or self.attention_over != "union" or self.attention_bound) and (
            self.kg != "attention" or self.kg_readout != "nodes"
        ):
            raise ModelError(
                "ModelConfig.attention_heads > 1, attention_over='each' and attention_bound take "
                "kg='attention', kg_readout='nodes'"
            )

    def softmaxes(self) -> int:
        """How many softmaxes over the objects the "nodes" attention hands the LSTM."""
        return self.attention_heads * (2 if self.attention_over == "each" else 1)

    def kg_width(self) -> int:
        """The width of what the graph (or its control row) adds to the LSTM's input."""
        if self.kg == "none":
            return self.gcn if self.detections else 0
        if self.kg_readout == "nodes":
            return N_TYPES * (self.softmaxes() if self.kg == "attention" else 1)
        return self.gcn


EDGE_WEIGHTS = ("binary", "ppmi", "ppmi_top5", "counts")
TOP_EDGES = 5  # "ppmi_top5": the strongest PPMI edges each node keeps


def normalized_adjacency(a: Tensor) -> Tensor:
    """D^-1/2 (A + I) D^-1/2 (D: the degrees of A + I) for (125, 125) or batched (B, 125, 125) A."""
    a_plus = a + torch.eye(a.shape[-1], dtype=a.dtype, device=a.device)
    d = a_plus.sum(-1).rsqrt()
    return d.unsqueeze(-1) * a_plus * d.unsqueeze(-2)


def pair_norm(x: Tensor) -> Tensor:
    """PairNorm (Zhao and Akoglu 2020) of node features x (n, d): centred over the nodes, then scaled
    so that the mean squared row norm is 1 (the total pairwise distance stays fixed layer to layer)."""
    x = x - x.mean(0)
    return x / x.square().sum(1).mean().add(1e-6).sqrt()


def masked_softmax(scores: Tensor, mask: Tensor) -> Tensor:
    """Softmax over the last dimension, over entries where mask is nonzero only; zero elsewhere. A row
    whose mask is all zero gets all-zero weights (no NaN, in the forward or the backward pass)."""
    keep = mask > 0
    s = scores.float().masked_fill(~keep, float("-inf"))
    top = s.amax(-1, keepdim=True).detach()
    top = torch.where(torch.isfinite(top), top, torch.zeros_like(top))
    e = torch.exp(s - top) * keep
    return e / e.sum(-1, keepdim=True).clamp_min(1e-30)


class CoVisibility:
    """The accumulated knowledge graph: how often each pair of the 125 types was visible together in
    the agent's training frames."""

    def __init__(self, n_types: int = N_TYPES):
        self.n_types = n_types
        self.counts = torch.zeros(n_types, n_types, dtype=torch.float64)

    def add(self, object_vectors) -> None:
        """(N, 125) 0/1 rows (one frame each): every pair visible together in a frame counts once."""
        v = torch.as_tensor(
            np.asarray(object_vectors) if not isinstance(object_vectors, Tensor) else object_vectors
        )
        v = (v.reshape(-1, self.n_types) > 0).float()
        # float32 sums of 0/1 products are exact up to 2**24 frames per call
        pairs = (v.T @ v).double()
        pairs.fill_diagonal_(0)
        self.counts += pairs

    def adjacency(self, edges: str = "binary") -> Tensor:
        """(125, 125) float32, symmetric, no self loops, zero where two types were never seen together.
        edges "binary": 1 on every pair ever seen together. "ppmi": max(0, log(c_ij S / (c_i c_j))) with
        c_i = sum_j c_ij and S = sum_i c_i, the co-occurrence PMI of word vectors: a pair seen together
        no more often than its types' frequencies predict gets no edge, so the frequent types do not
        tie every node to every other. "ppmi_top5": the PPMI edges among each node's 5 strongest (an
        edge either end keeps stays). "counts": c_ij / max c."""
        if edges not in EDGE_WEIGHTS:
            raise ModelError(f"edges={edges!r}: expected one of {', '.join(EDGE_WEIGHTS)}")
        c = self.counts.clone()
        c.fill_diagonal_(0)
        if edges == "binary":
            a = (c > 0).double()
        elif edges == "counts":
            a = c / c.max() if c.max() > 0 else c
        else:
            row = c.sum(1)
            total = row.sum()
            expected = torch.outer(row, row) / total.clamp_min(1)
            pmi = torch.log(c / expected.clamp_min(1e-300))
            a = torch.where(c > 0, pmi.clamp_min(0), torch.zeros_like(c))
            if edges == "ppmi_top5":
                keep = torch.zeros_like(a, dtype=torch.bool)
                keep.scatter_(1, a.topk(min(TOP_EDGES, len(a)), dim=1).indices, True)
                a = torch.where((keep | keep.T) & (a > 0), a, torch.zeros_like(a))
        return a.float()

    def state_dict(self) -> dict:
        return {"counts": self.counts.clone()}

    def load_state_dict(self, d: dict) -> None:
        counts = d.get("counts") if isinstance(d, dict) else None
        if not isinstance(counts, Tensor) or counts.shape != (self.n_types, self.n_types):
            got = tuple(counts.shape) if isinstance(counts, Tensor) else type(counts).__name__
            raise ModelError(
                f"co-visibility counts must be a ({self.n_types}, {self.n_types}) tensor, got {got}"
            )
        self.counts = counts.detach().to(torch.float64).clone()


@dataclass
class GraphTerms:
    """What the accumulated graph gives every sample alike: the GCN's node features H (125, d), Q's
    terms base (d,), D1 and D2 (125, d) (`KnowledgeGraph.q_terms`) and, with attention, the node
    scores of the three kinds of R_z node (in the view only, in the target only, in both) and of a
    node outside R_z ((125,) each). They depend on the weights and the adjacency only, so a rollout
    computes them once per update and every step (and the backward pass, through autograd) shares them."""

    node_features: Tensor
    base: Tensor
    d1: Tensor
    d2: Tensor
    scores: tuple[Tensor, Tensor, Tensor, Tensor] | None
    # kg_readout "nodes": +KG's u . Q_i + b as (c0 scalar, e1 (125,), e2 (125,)); +KG+Attention's
    # W1 Q_i + b1 as (W1 base + b1 (d,), W1 D1 (125, d), W1 D2 (125, d)) (`KnowledgeGraph.readout_terms`)
    readout: tuple[Tensor, Tensor, Tensor] | None = None


class KnowledgeGraph(nn.Module):
    """GCN over the 125 object types, the spatial features Q, and their mean or attention pool over
    R_z (module docstring: the closed form that never builds (B, 125, d) tensors)."""

    def __init__(self, cfg: ModelConfig, n_types: int = N_TYPES):
        super().__init__()
        d = cfg.gcn
        self.per_step, self.attention = cfg.kg_graph == "per_step", cfg.kg == "attention"
        self.all_nodes = cfg.attention_nodes == "all"
        self.nodes = cfg.kg_readout == "nodes"
        self.heads = cfg.attention_heads
        self.each = cfg.attention_over == "each"
        self.bound = float(cfg.attention_bound)
        self.softmaxes = cfg.softmaxes()
        self.norm = pair_norm if cfg.gcn_norm == "pair" else (lambda x: x)
        # H(0) = I, so the first layer's Â H(0) W(0) is Â W(0): W(0) is one row per type
        self.w0 = nn.Parameter(torch.randn(n_types, d) * (2 / n_types) ** 0.5)
        self.w1 = nn.Parameter(torch.randn(d, d) * (2 / d) ** 0.5)
        self.w2 = nn.Parameter(torch.randn(d, d) * (2 / d) ** 0.5)
        self.spatial_siamese = nn.Linear(d, d)  # W'_s
        self.spatial_fusion = nn.Linear(2 * d, d)  # W'_f
        if self.attention:
            self.score_hidden = nn.Linear(d, d)  # W1
            self.score = nn.Linear(d, cfg.softmaxes())  # w2, one per softmax
            if self.nodes and cfg.attention_context:  # W_c: the scores see I_t beside each node's Q
                self.score_context = nn.Linear(cfg.hidden, d, bias=False)
        elif self.nodes:
            self.node_readout = nn.Linear(d, 1)  # u, b: one scalar of Q per node (+KG)

    def node_features(self, a_hat: Tensor) -> Tensor:
        """H = the 3-layer GCN over Â (125, 125) -> (125, d)."""
        return self.layer_features(a_hat)[-1]

    def layer_features(self, a_hat: Tensor) -> list[Tensor]:
        """Each GCN layer's node features H(1), H(2), H(3) over Â, each (125, d), the norm of the
        config (PairNorm or none) applied after each propagation: what `node_features` computes, layer
        by layer, for the diagnostics (benchmarks/gcn_smoothing.py)."""
        h1 = F.relu(self.norm(a_hat @ self.w0))
        h2 = F.relu(self.norm(a_hat @ (h1 @ self.w1)))
        return [h1, h2, F.relu(self.norm(a_hat @ (h2 @ self.w2)))]

    def q_terms(self, h: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Q of a node whose GCN row is h (..., d): base + R_t D1 + R_g D2 -> base (d,), D1, D2 (..., d).
        A zero row (R = 0) gives ReLU(W'_s 0 + b) = ReLU(b): the constant that base collects."""
        d = h.shape[-1]
        wa, wb = self.spatial_fusion.weight[:, :d], self.spatial_fusion.weight[:, d:]
        on = F.relu(self.spatial_siamese(h))
        off = F.relu(self.spatial_siamese.bias)
        ca, cb = off @ wa.T, off @ wb.T
        return self.spatial_fusion.bias + ca + cb, on @ wa.T - ca, on @ wb.T - cb

    def scores(self, q: Tensor) -> Tensor:
        return self.score(F.relu(self.score_hidden(q))).squeeze(-1)

    def kind_scores(self, base: Tensor, d1: Tensor, d2: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Attention scores of an R_z node in the view only, in the target only, in both, and of a
        node outside R_z (its Q is base)."""
        q = torch.stack([base + d1, base + d2, base + d1 + d2, base.expand_as(d1)])
        return tuple(self.scores(q).unbind(0))

    def graph_terms(self, adjacency: Tensor) -> GraphTerms:
        """The accumulated graph's per-update terms (GraphTerms) from its (125, 125) adjacency."""
        if self.per_step:
            raise ModelError("kg_graph='per_step' has no per-update graph terms")
        node_features = self.node_features(normalized_adjacency(adjacency.to(self.w0.dtype)))
        base, d1, d2 = self.q_terms(node_features)  # d1, d2: (125, d)
        if self.nodes:
            return GraphTerms(node_features, base, d1, d2, None, self.readout_terms(base, d1, d2))
        scores = self.kind_scores(base, d1, d2) if self.attention else None  # (125,) each
        return GraphTerms(node_features, base, d1, d2, scores)

    def readout_terms(self, base: Tensor, d1: Tensor, d2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The linear first step of the "nodes" readout on Q_i = base + R_t,i D1_i + R_g,i D2_i, split
        the same way: +KG+Attention's W1 Q_i + b1, +KG's u . Q_i + b (GraphTerms.readout)."""
        if self.attention:
            w = self.score_hidden.weight
            return self.score_hidden(base), d1 @ w.T, d2 @ w.T
        u = self.node_readout.weight[0]
        return self.node_readout(base)[0], d1 @ u, d2 @ u

    def node_readout_of(self, r_t: Tensor, r_g: Tensor, terms: GraphTerms, context: Tensor) -> Tensor:
        """kg_readout "nodes" -> (B, 125), zero outside R_z. +KG: u . Q_i + b per R_z node.
        +KG+Attention: H_a = the softmax over R_z of w2 . ReLU(W1 Q_i + W_c I_t + b1) + b2, I_t the
        fused view and target (context). The scores are computed for the R_z nodes only (a sample sees
        about ten), never as a (B, 125, d) tensor."""
        r_z = torch.maximum(r_t, r_g)
        first, e1, e2 = terms.readout
        if not self.attention:
            return r_z * first + r_t * e1 + r_g * e2
        rows, nodes = r_z.nonzero(as_tuple=True)
        # W1 Q_i + b1 of an R_z node in the view only, in the target only, in both: (3 * 125, d); one
        # index_select per term (its backward an index_add, cheaper than advanced indexing's)
        kinds = torch.cat([first + e1, first + e2, first + e1 + e2])
        kind = (r_t[rows, nodes] + 2 * r_g[rows, nodes] - 1).long()  # 0, 1, 2
        n = r_z.shape[1]
        pre = kinds.index_select(0, kind * n + nodes)
        if hasattr(self, "score_context"):
            pre = pre + self.score_context(context).index_select(0, rows)
        picked = self.score(F.relu(pre))  # (nnz, softmaxes)
        if self.bound:
            picked = self.bound * torch.tanh(picked / self.bound)
        b, k = r_z.shape[0], self.softmaxes
        scores = torch.zeros(b, n, k, dtype=picked.dtype, device=picked.device)
        scores = scores.index_put((rows, nodes), picked).transpose(1, 2)  # (B, softmaxes, 125)
        if self.each:  # the first heads over the view's objects, the others over the target's
            mask = torch.cat(
                [r_t[:, None].expand(-1, self.heads, -1), r_g[:, None].expand(-1, self.heads, -1)], 1
            )
        else:
            mask = r_z[:, None, :]
        weights = masked_softmax(scores, mask)
        return weights[:, 0] if k == 1 else weights.reshape(b, k * n)

    def forward(
        self, r_t: Tensor, r_g: Tensor, graph: Tensor | GraphTerms | None, context: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """r_t, r_g: (B, 125) 0/1 float; graph: the accumulated graph, as its (125, 125) adjacency or
        as its `graph_terms` (None per step); context: the fused view and target I_t (B, hidden), which
        the "nodes" readout's attention scores see. Returns what the LSTM gets (the pooled Q (B, d), or
        the "nodes" readout (B, 125)), attention (B, 125) or None, and the node features H (125, d) of
        the accumulated graph (None per step)."""
        r_z = torch.maximum(r_t, r_g)
        if self.nodes:
            if graph is None or context is None:
                raise ModelError("kg_readout='nodes' needs the accumulated graph and the fused I_t")
            terms = graph if isinstance(graph, GraphTerms) else self.graph_terms(graph)
            out = self.node_readout_of(r_t, r_g, terms, context)
            attention = None
            if self.attention:  # (B, 125): with several softmaxes, their mean
                attention = out if self.softmaxes == 1 else out.view(len(out), self.softmaxes, -1).mean(1)
            return out, attention, terms.node_features
        both, t_only, g_only = r_t * r_g, r_t * (1 - r_g), (1 - r_t) * r_g
        if self.per_step:
            # the clique over R_z: every R_z row of Â is 1/|R_z| on the R_z columns, so every layer
            # maps the (shared) R_z row u to ReLU(u W); the first layer's u is the mean of W(0)'s rows
            u = F.relu((r_z @ self.w0) / r_z.sum(1, keepdim=True).clamp_min(1))
            u = F.relu(F.relu(u @ self.w1) @ self.w2)
            base, d1, d2 = self.q_terms(u)  # d1, d2: (B, d), the same for every R_z node of a sample
            node_features = None
            if self.attention:  # (B,) each: one score for all R_z nodes of a kind in a sample
                s_t, s_g, s_both, s_none = (s[:, None] for s in self.kind_scores(base, d1, d2))
        else:
            if graph is None:
                raise ModelError(
                    "kg_graph='accumulated' needs the (125, 125) adjacency of the co-visibility graph"
                )
            terms = graph if isinstance(graph, GraphTerms) else self.graph_terms(graph)
            node_features, base, d1, d2 = terms.node_features, terms.base, terms.d1, terms.d2
            if self.attention:
                s_t, s_g, s_both, s_none = terms.scores
        if self.attention:
            scores = t_only * s_t + g_only * s_g + both * s_both
            if self.all_nodes:  # every node; those outside R_z add their share of base below
                weights = torch.softmax((scores + (1 - r_z) * s_none).float(), 1)
            else:
                weights = masked_softmax(scores, r_z)
            attention = weights
        else:
            weights = r_z / r_z.sum(1, keepdim=True).clamp_min(1)
            attention = None
        weights = weights.to(d1.dtype)
        total = weights.sum(1, keepdim=True)  # 1, or 0 when R_z is empty
        if self.per_step:
            pooled = (
                total * base
                + (weights * r_t).sum(1, keepdim=True) * d1
                + (weights * r_g).sum(1, keepdim=True) * d2
            )
        else:
            pooled = total * base + (weights * r_t) @ d1 + (weights * r_g) @ d2
        return pooled, attention, node_features


class ActorCritic(nn.Module):
    """The learned agents' network (module docstring). forward(view, target, view_objects,
    target_objects, state, adjacency, scene) -> (logits (B, 10), value (B,), new state, extras)."""

    def __init__(self, cfg: ModelConfig, n_types: int = N_TYPES, n_actions: int = N_ACTIONS):
        super().__init__()
        cfg.validate()
        self.cfg, self.n_types, self.n_actions = cfg, n_types, n_actions
        self.encoder = Encoder(cfg.feature_dim, n_types) if cfg.pixels else None
        if cfg.pixels:  # its output standardized like the cached features (`encoder.standardize`)
            self.register_buffer("feature_mean", torch.zeros(cfg.feature_dim))
            self.register_buffer("feature_std", torch.ones(cfg.feature_dim))
        frames = cfg.history if cfg.arch == "ff" else 1
        self.siamese = nn.Linear(frames * cfg.feature_dim, cfg.hidden)  # W_s
        self.fusion = nn.Linear(2 * cfg.hidden, cfg.hidden)  # W_f
        self.kg = KnowledgeGraph(cfg, n_types) if cfg.kg != "none" else None
        self.detections = nn.Linear(2 * n_types, cfg.gcn) if cfg.detections else None  # W_d
        joint = cfg.hidden + cfg.kg_width()
        if cfg.arch == "lstm":
            self.lstm = nn.LSTMCell(joint, cfg.lstm)
            # the policy and value MLPs' first layers side by side: one matrix product for both
            self.heads_hidden = nn.Linear(cfg.lstm, 2 * cfg.head)
            self.policy = nn.Linear(cfg.head, n_actions)
            self.value = nn.Linear(cfg.head, 1)
            nn.init.normal_(self.policy.weight, std=0.01)  # a near-uniform policy at the start
            nn.init.zeros_(self.policy.bias)
        else:
            s, h = cfg.n_scenes, cfg.hidden

            def uniform(*shape, fan_in):
                return nn.Parameter(torch.empty(*shape).uniform_(-(fan_in**-0.5), fan_in**-0.5))

            self.scene_weight, self.scene_bias = (
                uniform(s, joint, h, fan_in=joint),
                uniform(s, h, fan_in=joint),
            )
            self.scene_policy = nn.Parameter(torch.randn(s, h, n_actions) * 0.01)
            self.scene_policy_bias = nn.Parameter(torch.zeros(s, n_actions))
            self.scene_value, self.scene_value_bias = uniform(s, h, 1, fan_in=h), uniform(s, 1, fan_in=h)

    def graph_terms(self, adjacency: Tensor | None) -> GraphTerms | Tensor | None:
        """What forward's `graph` may be instead of the adjacency: the accumulated graph's per-update
        terms, computed once (`GraphTerms`); the adjacency itself where there are none."""
        if self.kg is None or self.kg.per_step or adjacency is None:
            return adjacency
        return self.kg.graph_terms(adjacency)

    def initial_state(self, batch: int, device=None) -> tuple[Tensor, Tensor] | None:
        if self.cfg.arch != "lstm":
            return None
        z = torch.zeros(batch, self.cfg.lstm, device=device)
        return z, z.clone()

    def _features(self, x: Tensor, frames: int) -> Tensor:
        """(B, [frames,] 512) features, or uint8 views when pixels -> (B, frames * 512) float."""
        if self.encoder is not None:
            lead = x.shape[: x.dim() - 3]
            x = self.encoder(x.reshape(-1, *x.shape[-3:]))
            x = ((x - self.feature_mean) / self.feature_std.clamp_min(0.1)).reshape(*lead, -1)
        dtype = self.siamese.weight.dtype
        if frames > 1 and (x.dim() != 3 or x.shape[1] != frames):
            raise ModelError(f"ff views must be (B, history={frames}, features), got {tuple(x.shape)}")
        return x.reshape(x.shape[0], -1).to(dtype)

    def forward(
        self,
        view,
        target,
        view_objects,
        target_objects,
        state=None,
        graph=None,
        scene=None,
        target_rows=None,
    ):
        joint, extras = self.encode(view, target, view_objects, target_objects, graph, target_rows)
        logits, value, state = self.act(joint, state, scene)
        return logits, value, state, extras

    def encode(
        self, view, target, view_objects, target_objects, graph=None, target_rows=None
    ) -> tuple[Tensor, dict]:
        """The part of the network that does not recur over time: the siamese and fusion layers (and
        the knowledge graph's pooled Q) -> the joint input (B, J) of the LSTM or the scene layer. A
        trainer runs it once over a whole rollout's states (T * B rows) rather than step by step.
        `target_rows` (B,): `target` holds each distinct target once and row i's target is
        target[target_rows[i]] (a rollout's rows share a few targets: the siamese layer and the target's
        half of the fusion layer then run once per target, not once per row; not for FF)."""
        cfg = self.cfg
        frames = cfg.history if cfg.arch == "ff" else 1
        x_t = self._features(view, frames)
        x_g = self._features(target, 1)
        if frames > 1:  # Zhu et al. stack the target image as many times as the frames
            if target_rows is not None:
                raise ModelError("target_rows is not for ff (its target is stacked per frame)")
            x_g = x_g.repeat(1, frames)
        b = x_t.shape[0]
        if x_t.shape[1] != self.siamese.in_features or x_g.shape[1] != x_t.shape[1]:
            raise ModelError(
                f"view {tuple(x_t.shape)} and target {tuple(x_g.shape)} features do not fit "
                f"{self.siamese.in_features} inputs"
            )
        if target_rows is not None:
            # W_f [a, b] = W_f[:, :h] a + W_f[:, h:] b: the target's half once per distinct target
            h = self.fusion.in_features // 2
            s_t = F.relu(self.siamese(x_t))
            s_g = F.relu(self.siamese(x_g))
            w = self.fusion.weight
            joint = F.relu(F.linear(s_t, w[:, :h]) + F.linear(s_g, w[:, h:], self.fusion.bias)[target_rows])
        else:
            if x_g.shape[0] != b:
                raise ModelError(f"{x_g.shape[0]} targets for {b} views (without target_rows)")
            s = F.relu(self.siamese(torch.cat([x_t, x_g])))  # the siamese layer, both inputs in one product
            joint = F.relu(self.fusion(torch.cat([s[:b], s[b:]], 1)))
        attention = node_features = None
        if self.kg is not None:
            r_t = (view_objects > 0).to(self.kg.w0.dtype)
            r_g = (target_objects > 0).to(self.kg.w0.dtype)
            pooled, attention, node_features = self.kg(r_t, r_g, graph, context=joint)
            joint = torch.cat([joint, pooled.to(joint.dtype)], 1)
        elif self.detections is not None:
            r = torch.cat([view_objects, target_objects], 1) > 0
            detected = F.relu(self.detections(r.to(self.detections.weight.dtype)))
            joint = torch.cat([joint, detected.to(joint.dtype)], 1)
        return joint, {"attention": attention, "node_features": node_features}

    def act(self, joint: Tensor, state=None, scene=None):
        """One step of the recurrent part and the heads: joint (B, J) -> logits (B, 10), value (B,),
        the new LSTM state (None for FF, whose scene-specific heads read `scene`)."""
        if self.cfg.arch == "lstm":
            h, c = self.recur(joint, state)
            logits, value = self.heads(h)
            return logits, value, (h, c)
        logits, value = self._scene_heads(joint, scene)
        return logits, value, None

    def recur(self, joint: Tensor, state=None) -> tuple[Tensor, Tensor]:
        """The LSTM cell: (h, c) after this step (from zeros when state is None)."""
        if state is None:
            state = self.initial_state(joint.shape[0], joint.device)
        _, h, c = self._lstm(joint[None], state)
        # the state keeps its own dtype (fp32): under bf16 autocast on a CPU with native bf16, or on
        # CUDA, the fused LSTM returns bf16, which the callers' fp32 state buffers cannot take
        return h[0].to(state[0].dtype), c[0].to(state[1].dtype)

    def recur_sequence(self, joint: Tensor, state=None) -> Tensor:
        """The LSTM over whole sequences: joint (T, N, J), the state (h, c) (N, lstm) before their first
        step (zeros when None) -> the outputs h (T, N, lstm), in one fused call."""
        if state is None:
            state = self.initial_state(joint.shape[1], joint.device)
        return self._lstm(joint, state)[0]

    def recur_packed(self, joint: Tensor, batch_sizes: Tensor, state) -> Tensor:
        """The LSTM over sequences of different lengths, packed as torch's PackedSequence packs them:
        joint (P, J) holds step 0 of every sequence, then step 1 of those still going, ... (longest
        first), `batch_sizes` (CPU int64) how many at each step; the state (h, c) (N, lstm) before the
        first step, in the same order -> the outputs h (P, lstm). Only real steps are computed: padded
        to the longest, a TSE batch is some three quarters padding (measured)."""
        return self._lstm(joint, state, batch_sizes)[0]

    def _lstm(self, joint: Tensor, state, batch_sizes: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """torch's fused LSTM (oneDNN on the CPU, cuDNN on CUDA) with the LSTMCell's own weights (the
        checkpoints keep LSTMCell's names), over joint (T, N, J), or packed sequences when `batch_sizes`
        is given. The same function as the cell to float rounding, and about twice as fast on the CPU
        even for one step (measured at 140 x 256, one thread: 1.2 against 2.5 ms per step; a 20-step
        sequence forward and backward 76 against 155 ms). The trainer's unroll across episode ends keeps
        the cell (`agent.Model.unroll`)."""
        cell = self.lstm
        h, c = state
        weights = [cell.weight_ih, cell.weight_hh, cell.bias_ih, cell.bias_hh]
        # in the weights' dtype: CUDA's autocast does not cast torch.lstm's inputs (it does LSTMCell's)
        dtype = cell.weight_ih.dtype
        joint, h, c = joint.to(dtype).contiguous(), h.to(dtype)[None], c.to(dtype)[None]
        training = torch.is_grad_enabled()  # no workspace for a backward pass that will not come
        # CPU autocast runs torch.lstm in bf16, and oneDNN has no bf16 LSTM primitive on a CPU without
        # native bf16 (an AVX2-only AMD EPYC: "could not create a primitive descriptor"); there the
        # LSTM runs in fp32 and the rest of the network stays under autocast.
        fp32_lstm = joint.device.type == "cpu" and not _CPU_HAS_BF16 and torch.is_autocast_enabled("cpu")
        with torch.autocast("cpu", enabled=False) if fp32_lstm else contextlib.nullcontext():
            if batch_sizes is not None:  # torch.lstm's packed overload: (data, batch_sizes, hx, ...)
                return torch.lstm(joint, batch_sizes, (h, c), weights, True, 1, 0.0, training, False)
            return torch.lstm(joint, (h, c), weights, True, 1, 0.0, training, False, False)

    def heads(self, h: Tensor) -> tuple[Tensor, Tensor]:
        """Policy logits and value from LSTM outputs h (..., lstm): one product for both MLPs' first
        layers; runs on a whole rollout's outputs at once."""
        hidden = F.relu(self.heads_hidden(h))
        head = self.cfg.head
        return self.policy(hidden[..., :head]), self.value(hidden[..., head:]).squeeze(-1)

    def _scene_heads(self, joint: Tensor, scene: Tensor | None) -> tuple[Tensor, Tensor]:
        """Scene-specific layer and heads: the batch sorted by scene, one product per scene present
        (a loop over at most n_scenes scenes, never over samples), then put back in order."""
        if scene is None:
            raise ModelError("arch='ff' needs scene, the (B,) training-kitchen index of every sample")
        scene = torch.as_tensor(scene, dtype=torch.long).reshape(-1)
        if scene.shape[0] != joint.shape[0]:
            raise ModelError(f"scene has {scene.shape[0]} entries for a batch of {joint.shape[0]}")
        if len(scene) and (int(scene.min()) < 0 or int(scene.max()) >= self.cfg.n_scenes):
            raise ModelError(f"scene indices must lie in 0..{self.cfg.n_scenes - 1}")
        order = torch.argsort(scene, stable=True)
        counts = torch.bincount(scene, minlength=self.cfg.n_scenes).tolist()
        logits, values = [], []
        for k, part in enumerate(joint[order].split(counts)):
            if len(part) == 0:
                continue
            h = F.relu(part @ self.scene_weight[k].to(part.dtype) + self.scene_bias[k])
            logits.append(h @ self.scene_policy[k].to(h.dtype) + self.scene_policy_bias[k])
            values.append(h @ self.scene_value[k].to(h.dtype) + self.scene_value_bias[k])
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(len(order))
        return torch.cat(logits)[inverse], torch.cat(values)[inverse].squeeze(-1)


def make_model(cfg: ModelConfig) -> ActorCritic:
    """The network of a config; ModelError (a ValueError) naming the bad field."""
    if not isinstance(cfg, ModelConfig):
        raise ModelError(f"make_model needs a ModelConfig, got {type(cfg).__name__}")
    cfg.validate()
    return ActorCritic(cfg)
