"""Learner speed of the actor-critic networks: frames/s of one forward + backward pass (and of a
forward pass without autograd, as when acting) at batch 1024 on per-state features, in fp32 and under
bf16 autocast. A frame is one agent step. Run it alone (under the benchmark lock): it times the CPU.

    flock /tmp/kgnav_bench.lock .venv/bin/python benchmarks/models_speed.py
"""

import argparse
import time

import torch

from kgnavbench.models import FEATURE_DIM, N_TYPES, ModelConfig, make_model

MODELS = {
    "lstm": ModelConfig(arch="lstm"),
    "ff": ModelConfig(arch="ff"),
    "lstm + kg mean": ModelConfig(kg="mean"),
    "lstm + kg attention": ModelConfig(kg="attention"),
    "lstm + kg attention, per-step graph": ModelConfig(kg="attention", kg_graph="per_step"),
}


def batch_inputs(cfg: ModelConfig, b: int) -> dict:
    g = torch.Generator().manual_seed(0)
    shape = (b, cfg.history, FEATURE_DIM) if cfg.arch == "ff" else (b, FEATURE_DIM)
    # about 3.3 types are visible per view in the kitchens: 3 / 125 of the entries are ones
    objects = [(torch.rand(b, N_TYPES, generator=g) < 3 / N_TYPES).float() for _ in range(2)]
    adjacency = (torch.rand(N_TYPES, N_TYPES, generator=g) < 0.1).float()
    return dict(
        view=torch.rand(shape, generator=g),
        target=torch.rand(b, FEATURE_DIM, generator=g),
        view_objects=objects[0],
        target_objects=objects[1],
        graph=torch.maximum(adjacency, adjacency.T).fill_diagonal_(0),
        scene=torch.randint(0, cfg.n_scenes, (b,), generator=g),
    )


def timed(step, seconds: float) -> float:
    """Seconds per call: two warm-up calls, then calls until `seconds` have passed (at least 2)."""
    step()
    step()
    n, start = 0, time.perf_counter()
    while n < 2 or time.perf_counter() - start < seconds:
        step()
        n += 1
    return (time.perf_counter() - start) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--seconds", type=float, default=3.0, help="time per figure")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    b = args.batch
    print(f"learner frames/s at batch {b}, {torch.get_num_threads()} threads, torch {torch.__version__}")
    print(f"{'model':38s} {'params':>9s} {'dtype':>6s} {'fwd+bwd frames/s':>17s} {'fwd frames/s':>13s}")
    for name, cfg in MODELS.items():
        torch.manual_seed(0)
        model = make_model(cfg)
        x = batch_inputs(cfg, b)
        state = model.initial_state(b)
        n_params = sum(p.numel() for p in model.parameters())
        for dtype in ("fp32", "bf16"):
            autocast = dtype == "bf16"

            def train_step():
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):  # noqa: B023
                    logits, value, _, _ = model(**x, state=state)  # noqa: B023
                (logits.float().logsumexp(1).mean() + value.float().square().mean()).backward()
                model.zero_grad(set_to_none=True)  # noqa: B023

            @torch.no_grad()
            def act_step():
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):  # noqa: B023
                    model(**x, state=state)  # noqa: B023

            learn = b / timed(train_step, args.seconds)
            act = b / timed(act_step, args.seconds)
            print(f"{name:38s} {n_params:9,d} {dtype:>6s} {learn:17,.0f} {act:13,.0f}", flush=True)


if __name__ == "__main__":
    main()
