"""Does the knowledge graph carry knowledge? Diagnostics of a KG checkpoint's GCN and attention.

For each KG checkpoint given (default: every `zoo/kg_attention-*/best.pt`), over the object types that
have a co-visibility edge, it prints:
- the graph: its nodes, edges, density and the edge weights the model trained on (`kg_edges`);
- per GCN layer, the share of the variance of the centred node features along their first principal
  direction, for the checkpoint's weights and for freshly initialised ones (torch seed 0) on the same
  graph; and the same share for the centred rows of Â³ (the graph alone). A share near 100% at the
  third layer for fresh weights too says the flattening comes from propagating three times over a
  dense graph (over-smoothing), not from training;
- the last layer's effective rank (exp of the entropy of its normalised singular values, Roy and
  Vetterli 2007; 1 for one direction) and the mean pairwise cosine of its (uncentred) rows;
- structure: two types are *related* when one is the other's receptacle in some kitchen, or their
  centres (the nearest instances) lie within 1.5 m in at least half of the kitchens that hold both
  (all 30 kitchens); the share of related pairs among each node's 3 nearest neighbours (cosine of the
  centred last-layer features) against the share among all pairs, and their ratio (issue 41 asks
  for at least 2.0); and the 3 nearest neighbours of 10 named types;
- on FloorPlan1, over all its targets and all its states (the view of every state toward each
  target's image): the distinct vectors per target of what the graph hands the LSTM (distinct at
  1e-3), and with attention the distinct attention vectors per target and their mean entropy (nats,
  states with objects in view or target); with several softmaxes (heads, or one over each image's
  objects), those of their mean, and each one's distinct vectors and entropy; with one softmax over
  the target image's objects (attention_over "each"), the weight it puts on the target's own object
  type, against a uniform softmax's (1 / the target image's objects). (A share of the attention's
  mean on the target-only objects is no criterion there: with two averaged softmaxes it is at most 0.5
  by construction.)

Every layer's features come from the model's own code (`KnowledgeGraph.layer_features`, the path of
`node_features`); tests/test_models.py checks that the last layer is `node_features` on a shipped
checkpoint.

`--edges EDGES` also prints the GCN figures for fresh weights on the checkpoint's counts weighted as
EDGES (binary, ppmi, counts): what another graph would give before training.
Run: .venv/bin/python benchmarks/gcn_smoothing.py [CHECKPOINT ...] [--edges ppmi]
"""

import argparse
import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from kgnavbench import models
from kgnavbench.files import first_line
from kgnavbench.kitchens import KITCHEN_NAMES, load_kitchen, object_types
from kgnavbench.runs import TrainError, load_checkpoint
from kgnavbench.vecenv import build_space

ZOO = Path(__file__).resolve().parents[1] / "zoo"
NAMED = (
    "Fridge", "Egg", "StoveBurner", "Pan", "Sink", "Faucet", "Toaster", "Bread", "Vase", "Shelf",
    "Statue", "CoffeeMachine", "Microwave", "Cabinet",
)  # fmt: skip
NEAR = 1.5  # metres: the paper's visibility distance
TOLERANCE = 1e-3  # two attention vectors are distinct when some weight differs by more


def first_direction_share(x: torch.Tensor) -> float:
    """% of the variance of the rows of x (centred) along their first principal direction."""
    x = x.double() - x.double().mean(0)
    s = torch.linalg.svdvals(x) ** 2
    if s.sum() == 0:  # every row the same (e.g. all zero after the ReLU): no direction to speak of
        return float("nan")
    return 100 * (s[0] / s.sum()).item()


def effective_rank(x: torch.Tensor) -> float:
    """exp(entropy of the normalised singular values of the centred rows of x)."""
    s = torch.linalg.svdvals(x.double() - x.double().mean(0))
    if s.sum() == 0:
        return float("nan")
    p = s / s.sum()
    p = p[p > 0]
    return math.exp(-(p * p.log()).sum().item())


def mean_pairwise_cosine(x: torch.Tensor) -> float:
    x = F.normalize(x.double(), dim=1)
    c = x @ x.T
    n = len(x)
    return ((c.sum() - c.diagonal().sum()) / (n * (n - 1))).item()


def layers(kg, a_hat: torch.Tensor) -> list[torch.Tensor]:
    """Each GCN layer's node features, from the model's own code (`KnowledgeGraph.layer_features`, the
    path `node_features` takes, PairNorm included where the config has it): never a copy of it, which
    would measure a network the model does not compute."""
    return kg.layer_features(a_hat)


def related_types() -> set[frozenset[str]]:
    """Pairs of types related in the real kitchens: receptacle and content in some kitchen, or nearest
    instances' centres within NEAR metres in at least half the kitchens that hold both."""
    related: set[frozenset[str]] = set()
    both: dict[frozenset[str], int] = {}
    near: dict[frozenset[str], int] = {}
    for name in KITCHEN_NAMES:
        k = load_kitchen(name)
        by_id = {o.id: o for o in k.objects}
        centres: dict[str, list[tuple[float, float]]] = {}
        for o in k.objects:
            centres.setdefault(o.type, []).append(o.center)
            if o.parent in by_id and by_id[o.parent].type != o.type:
                related.add(frozenset((o.type, by_id[o.parent].type)))
        types = sorted(centres)
        for i, a in enumerate(types):
            for b in types[i + 1 :]:
                pair = frozenset((a, b))
                both[pair] = both.get(pair, 0) + 1
                d = min(math.dist(p, q) for p in centres[a] for q in centres[b])
                near[pair] = near.get(pair, 0) + (d <= NEAR)
    related |= {pair for pair, n in both.items() if 2 * near.get(pair, 0) >= n}
    return related


def structure(h: torch.Tensor, names: list[str], related) -> tuple[float, float, dict[str, list[str]]]:
    """(share of related pairs among each node's 3 nearest neighbours, share among all pairs, the
    neighbours of every node) by cosine of the centred rows of h."""
    x = F.normalize(h.double() - h.double().mean(0), dim=1)
    cos = x @ x.T
    cos.fill_diagonal_(-2)
    top = cos.topk(3, dim=1).indices.tolist()
    neighbours = {names[i]: [names[j] for j in row] for i, row in enumerate(top)}
    hits = [frozenset((a, b)) in related for a, nbrs in neighbours.items() for b in nbrs]
    pairs = [frozenset((a, b)) in related for i, a in enumerate(names) for b in names[i + 1 :]]
    return sum(hits) / len(hits), sum(pairs) / len(pairs), neighbours


def attention_figures(net, covis, space) -> dict[str, float]:
    """The FloorPlan1 figures of the module docstring for one network."""
    with torch.no_grad():
        graph = net.graph_terms(covis.adjacency(net.cfg.kg_edges))
        features, objects = space.features_t, space.objects_t
        hidden = net.cfg.hidden
        channel, attention, entropy, own, uniform = [], [], [], [], []
        k = net.cfg.softmaxes() if net.cfg.kg == "attention" and net.cfg.kg_readout == "nodes" else 1
        # attention_over "each": the first heads over the view's objects, the others over the target's
        each = k > 1 and net.cfg.attention_over == "each"
        target_softmax = net.cfg.attention_heads if each else None
        per_softmax = [([], []) for _ in range(k)] if k > 1 else []  # (distinct, entropies) each
        for r, dest in enumerate(space.destination):
            lo, hi = space.offsets[space.target_kitchen[r]], space.offsets[space.target_kitchen[r] + 1]
            states = torch.arange(int(lo), int(hi))
            n = len(states)
            joint, extras = net.encode(
                features[states],
                features[[int(dest)]],
                objects[states],
                objects[[int(dest)]].expand(n, -1),
                graph,
                target_rows=torch.zeros(n, dtype=torch.long),
            )
            channel.append(distinct(joint[:, hidden:]))
            a = extras["attention"]
            if a is None:
                continue
            attention.append(distinct(a))
            r_t, r_g = objects[states] > 0, objects[[int(dest)]].expand(n, -1) > 0
            some = (r_t | r_g).any(1)
            ent = -(a * a.clamp_min(1e-30).log()).sum(1)
            entropy += ent[some].tolist()
            if target_softmax is not None and bool(r_g[0, space.target_type[r]]):
                # the target softmax's weight on the target's own object type, and a uniform one's
                w = joint[:, hidden:].reshape(n, k, -1)[:, target_softmax].double()
                own.append(w[:, int(space.target_type[r])].mean().item())
                uniform.append(1.0 / r_g[0].sum().item())
            for j, (kinds, ents) in enumerate(per_softmax):
                w = joint[:, hidden:].reshape(n, k, -1)[:, j].float()
                some = w.sum(1) > 0.5  # a softmax over an empty set of objects is all zero
                kinds.append(distinct(w))
                ents += (-(w * w.clamp_min(1e-30).log()).sum(1))[some].tolist()
    out = {"targets": len(channel), "channel": np.mean(channel), "channel_min": min(channel)}
    if attention:
        out |= {
            "attention": np.mean(attention),
            "attention_min": min(attention),
            "entropy": float(np.mean(entropy)),
            "target_own": float(np.mean(own)) if own else float("nan"),
            "target_uniform": float(np.mean(uniform)) if uniform else float("nan"),
            "own_targets": len(own),
            "per_softmax": [(np.mean(kinds), float(np.mean(ents))) for kinds, ents in per_softmax],
        }
    return out


def distinct(x: torch.Tensor) -> int:
    return len(torch.unique(torch.round(x.double() / TOLERANCE), dim=0))


def load(path: Path, ap) -> tuple[dict, models.CoVisibility, models.ActorCritic, models.ActorCritic]:
    try:  # checksummed, weights only, as every loader of the package reads a checkpoint
        ck = load_checkpoint(path)
    except TrainError as e:
        ap.error(str(e))
    try:
        covis = models.CoVisibility()
        covis.load_state_dict(ck["covis"])
        trained = models.make_model(models.ModelConfig(**ck["model_config"]))
        trained.load_state_dict(ck["model"])
        torch.manual_seed(0)
        fresh = models.make_model(models.ModelConfig(**ck["model_config"]))
    except (models.ModelError, RuntimeError, KeyError, TypeError, ValueError) as e:
        ap.error(f"{path}: does not fit its model ({first_line(e)})")
    if getattr(trained, "kg", None) is None or trained.kg.per_step:
        ap.error(f"{path}: its model has no accumulated knowledge graph (not a KG row's checkpoint)")
    return ck, covis, trained.eval(), fresh.eval()


def gcn_line(label: str, kg, a_hat, nodes, names, related) -> list[str]:
    with torch.no_grad():
        hs = [h[nodes] for h in layers(kg, a_hat)]
    near, base, neighbours = structure(hs[-1], names, related)
    return [
        f"  {label}: first direction L1/L2/L3 "
        + "/".join(f"{first_direction_share(h):.2f}" for h in hs)
        + f" %; L3 effective rank {effective_rank(hs[-1]):.2f}, mean pairwise cosine "
        f"{mean_pairwise_cosine(hs[-1]):.4f}; related among 3 nearest neighbours {near:.1%} against "
        f"{base:.1%} of all pairs: ratio {near / base:.2f}",
        *(
            f"    {t}: {', '.join(neighbours[t])}"
            for t in NAMED
            if t in neighbours and label.startswith("trained")
        ),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="*", type=Path)
    ap.add_argument("--edges", action="append", default=[], choices=models.EDGE_WEIGHTS)
    ap.add_argument("--no-attention", action="store_true", help="skip the FloorPlan1 figures")
    args = ap.parse_args()
    torch.set_num_threads(1)
    paths = args.checkpoints or sorted(ZOO.glob("kg_attention-*/best.pt"))
    if not paths:
        ap.error(f"no checkpoints given and none in {ZOO}/kg_attention-*/best.pt")
    related = related_types()
    type_names = object_types()
    space = None if args.no_attention else build_space(["FloorPlan1"], targets="all")
    for path in paths:
        ck, covis, trained, fresh = load(path, ap)
        cfg = trained.cfg
        adjacency = covis.adjacency(cfg.kg_edges)
        nodes = adjacency.sum(1) > 0
        n = int(nodes.sum())
        if n < 4:
            ap.error(f"{path}: its co-visibility graph has fewer than 4 nodes with an edge")
        names = [type_names[i] for i in nodes.nonzero().squeeze(1).tolist()]
        sub = related & {frozenset((a, b)) for i, a in enumerate(names) for b in names[i + 1 :]}
        edges = int((adjacency[nodes][:, nodes] > 0).sum().item()) // 2
        print(
            f"{path}: {ck['frames']:,} frames, kg={cfg.kg}, edges={cfg.kg_edges}, readout="
            f"{cfg.kg_readout}; {n} nodes, {edges} edges, density {edges / (n * (n - 1) / 2):.0%}, "
            f"{len(sub) / (n * (n - 1) / 2):.1%} of the pairs related"
        )
        a_hat = models.normalized_adjacency(adjacency)
        graph_only = first_direction_share(torch.linalg.matrix_power(a_hat, 3)[nodes][:, nodes])
        print(f"  graph alone: centred rows of Â³, first direction {graph_only:.2f} %")
        for line in gcn_line("trained", trained.kg, a_hat, nodes, names, related):
            print(line)
        print(gcn_line("fresh", fresh.kg, a_hat, nodes, names, related)[0])
        for edges_kind in args.edges:
            other = covis.adjacency(edges_kind)
            keep = other.sum(1) > 0
            other_names = [type_names[i] for i in keep.nonzero().squeeze(1).tolist()]
            line = gcn_line(
                f"fresh, {edges_kind}",
                fresh.kg,
                models.normalized_adjacency(other),
                keep,
                other_names,
                related,
            )
            print(line[0])
        if space is not None:
            f = attention_figures(trained, covis, space)
            print(
                f"  FloorPlan1, {f['targets']} targets: distinct graph-channel vectors per target "
                f"{f['channel']:.0f} (fewest {f['channel_min']})"
            )
            if "attention" in f:
                print(
                    f"  attention: distinct vectors per target {f['attention']:.0f} (fewest "
                    f"{f['attention_min']}), mean entropy {f['entropy']:.3f} nats"
                    + (" (the mean of its softmaxes)" if f["per_softmax"] else "")
                )
                if f["own_targets"]:
                    print(
                        f"  the target softmax's weight on the target's own object: {f['target_own']:.3f} "
                        f"(uniform over the target image's objects: {f['target_uniform']:.3f}), mean over "
                        f"{f['own_targets']} targets and all their states"
                    )
                for j, (kinds, ent) in enumerate(f["per_softmax"]):
                    print(
                        f"    softmax {j}: distinct vectors per target {kinds:.0f}, "
                        f"mean entropy {ent:.3f} nats"
                    )


if __name__ == "__main__":
    main()
