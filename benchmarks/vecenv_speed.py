"""Steps per second through the Gymnasium vector env (kgnavbench/vecenv.py) with feature observations.

`NavigationVectorEnv` over the 20 training kitchens (sub-env i in kitchen i mod 20), random actions
from all ten (so episodes end by Stop and the same-step autoreset runs and is timed), every step's
observations gathered into fresh arrays (512 features of the view and of the target, 125 + 125 object
types per sub-env) and its infos built. One process, one thread. Run:
.venv/bin/python benchmarks/vecenv_speed.py [--envs 140,1280] [--views]
"""

import argparse
import time

import numpy as np
import torch

from kgnavbench.vecenv import NavigationVectorEnv


def measure(envs: NavigationVectorEnv, seconds: float) -> tuple[float, float]:
    envs.reset(seed=0)
    n = envs.num_envs
    table = np.random.default_rng(0).integers(0, 10, size=(256, n))
    steps = episodes = k = 0
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        _, _, terminated, truncated, _ = envs.step(table[k % 256])
        episodes += int((terminated | truncated).sum())
        steps += n
        k += 1
    return steps / elapsed, episodes / elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", default="140,1280", help="num_envs values, comma-separated")
    ap.add_argument("--kitchens", default="train", help="a split or a kitchen (default: train)")
    ap.add_argument("--views", action="store_true", help="observations include the 84x84 views")
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    for n in (int(x) for x in args.envs.split(",")):
        start = time.perf_counter()
        envs = NavigationVectorEnv(num_envs=n, kitchens=args.kitchens, views=args.views)
        built = time.perf_counter() - start
        rate, episodes = measure(envs, args.seconds)
        print(
            f"{n:5d} envs ({args.kitchens}{', views' if args.views else ''}): {rate:10,.0f} steps/s  "
            f"{episodes:8,.0f} episodes/s  (built in {built:.1f} s)",
            flush=True,
        )


if __name__ == "__main__":
    main()
