"""How one-dimensional the KG rows' GCN node features are, layer by layer, trained and untrained.

For each KG checkpoint given (default: every `zoo/kg_attention-*/best.pt`) it prints, over the object
types that have a co-visibility edge: their number, the edges between them and the density; for each
of the three GCN layers, the share of the variance of the centred node features along their first
principal direction, for the checkpoint's weights and for freshly initialised ones (torch seed 0) on
the same graph; and the same share for the centred rows of Â³ (Â: the normalised adjacency with self
loops), the graph alone. A share near 100% at the third layer for fresh weights too says the
flattening comes from propagating three times over a dense graph (over-smoothing), not from training.
Run: .venv/bin/python benchmarks/gcn_smoothing.py [CHECKPOINT ...]
"""

import argparse
from pathlib import Path

import torch
import torch.nn.functional as F

from kgnavbench import models
from kgnavbench.files import first_line
from kgnavbench.runs import TrainError, load_checkpoint

ZOO = Path(__file__).resolve().parents[1] / "zoo"


def first_direction_share(x: torch.Tensor) -> float:
    """% of the variance of the rows of x (centred) along their first principal direction."""
    x = x.double() - x.double().mean(0)
    s = torch.linalg.svdvals(x) ** 2
    if s.sum() == 0:  # every row the same (e.g. all zero after the ReLU): no direction to speak of
        return float("nan")
    return 100 * (s[0] / s.sum()).item()


def layer_shares(kg, a_hat: torch.Tensor, nodes: torch.Tensor) -> list[float]:
    """first_direction_share of each GCN layer's node features (models.KnowledgeGraph.node_features,
    written out layer by layer), over the rows `nodes`."""
    h1 = F.relu(a_hat @ kg.w0)
    h2 = F.relu(a_hat @ (h1 @ kg.w1))
    h3 = F.relu(a_hat @ (h2 @ kg.w2))
    return [first_direction_share(h[nodes]) for h in (h1, h2, h3)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="*", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    paths = args.checkpoints or sorted(ZOO.glob("kg_attention-*/best.pt"))
    if not paths:
        ap.error(f"no checkpoints given and none in {ZOO}/kg_attention-*/best.pt")
    print("checkpoint | nodes | edges | density | trained L1/L2/L3 (%) | fresh L1/L2/L3 (%) | centred Â³ (%)")
    for path in paths:
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
        if getattr(trained, "kg", None) is None:
            ap.error(f"{path}: its model has no knowledge graph (not a KG row's checkpoint)")
        adjacency = covis.adjacency()
        nodes = adjacency.sum(1) > 0
        n = int(nodes.sum())
        if n < 2:
            ap.error(f"{path}: its co-visibility graph has no edge")
        edges = int(adjacency[nodes][:, nodes].sum().item()) // 2  # symmetric 0/1, no self loops
        density = edges / (n * (n - 1) / 2)
        a_hat = models.normalized_adjacency(adjacency)
        with torch.no_grad():
            shares = layer_shares(trained.kg, a_hat, nodes), layer_shares(fresh.kg, a_hat, nodes)
            graph = first_direction_share(torch.linalg.matrix_power(a_hat, 3)[nodes][:, nodes])
        print(
            f"{path} | {n} | {edges} | {density:.0%} | "
            + " | ".join("/".join(f"{s:.3f}" for s in layer) for layer in shares)
            + f" | {graph:.2f}"
        )


if __name__ == "__main__":
    main()
