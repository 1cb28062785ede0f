"""Random walk: every action drawn uniformly from the ten (Stop included), independent of what it sees.

The paper's first row of Table I. Copy this file to start a new baseline: a plugin is DESCRIPTION,
an optional Config dataclass and make_policy(config, spec) returning an object with reset() and act().
"""

from dataclasses import dataclass

import numpy as np

DESCRIPTION = "uniformly random actions, Stop included"


@dataclass
class Config:
    stop_probability: float = 0.1  # chance of Stop per step; the rest is spread over the other nine


class RandomWalk:
    def __init__(self, config: Config, n_actions: int, seed: int):
        if not 0.0 <= config.stop_probability <= 1.0:
            raise ValueError(f"stop_probability must be in [0, 1], not {config.stop_probability}")
        self.rng = np.random.default_rng(seed)
        stop = n_actions - 1  # Stop is the last action
        self.p = np.full(n_actions, (1 - config.stop_probability) / (n_actions - 1))
        self.p[stop] = config.stop_probability

    def reset(self, agent: str) -> None:
        pass  # no memory

    def act(self, observations: dict, infos: dict) -> dict:
        agents = list(observations)
        actions = self.rng.choice(len(self.p), size=len(agents), p=self.p)
        return {agent: int(a) for agent, a in zip(agents, actions)}


def make_policy(config: Config, spec) -> RandomWalk:
    return RandomWalk(config, spec.n_actions, spec.seed)
