"""Agent-steps per second through the PettingZoo ParallelEnv with cached views.

Random actions (all ten; a wrong Stop is a no-op, so agents stay live until they stop on their target;
when all have, the env is reset, and that time counts), one env per measurement,
observations and infos built every step as a training loop would receive them. The state graph
comes from the cache (built first if missing). Run: .venv/bin/python benchmarks/env_speed.py
"""

import argparse
import time

import numpy as np

from kgnavbench.env import parallel_env
from kgnavbench.tasks import load_tasks


def measure(tasks, n_agents: int, seconds: float) -> float:
    env = parallel_env(
        kitchen=tasks.kitchen, n_agents=n_agents, stop_ends=False, max_steps=10**9, tasks=tasks
    )
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    table = rng.integers(0, 10, size=(1024, n_agents))
    steps, k = 0, 0
    start = time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        if not env.agents:  # every agent has stopped on its target: next episodes (reset is timed too)
            env.reset()
        actions = dict(zip(env.agents, table[k % 1024].tolist()))
        env.step(actions)
        steps += len(actions)
        k += 1
    return steps / elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kitchens", default="FloorPlan1,FloorPlan7,FloorPlan16,FloorPlan28")
    ap.add_argument("--agents", default="1,8,32,100,256")
    ap.add_argument("--seconds", type=float, default=2.0)
    args = ap.parse_args()
    agent_counts = [int(a) for a in args.agents.split(",")]
    results = {n: [] for n in agent_counts}
    for name in args.kitchens.split(","):
        tasks = load_tasks(name)
        line = [f"{name:12s}"]
        for n in agent_counts:
            rate = measure(tasks, n, args.seconds)
            results[n].append(rate)
            line.append(f"{n:4d} agents {rate:9,.0f}")
        print("  ".join(line), "agent-steps/s", flush=True)
    for n in agent_counts:
        r = results[n]
        print(f"{n:4d} agents per env: mean {np.mean(r):9,.0f} agent-steps/s (min {min(r):,.0f})")


if __name__ == "__main__":
    main()
