"""IL: imitation learning alone, Table I's "IL" row.

The LSTM A3C network trained only by cross-entropy on one expert trajectory per training target (the
paper's walk-back from the destination by default; il_expert=shortest for BFS-optimal paths from a
training start). No reinforcement: frames count the expert steps trained on.

    kgnavbench train --method imitation --frames 1000000
    kgnavbench eval --method imitation --run runs/train/imitation-...
"""

from dataclasses import dataclass

from kgnavbench.models import ModelConfig
from kgnavbench.train import TrainOptions, learn, load_policy

DESCRIPTION = "imitation learning only: cross-entropy on expert trajectories (LSTM network)"


@dataclass
class Config(TrainOptions):
    il: bool = True


def model_config(config: Config) -> ModelConfig:
    return ModelConfig(arch="lstm", kg="none", hidden=config.hidden, lstm=config.lstm)


def train(config: Config, run) -> None:
    learn(run, config, model_config(config), rl=False)


def make_policy(config: Config, spec):
    return load_policy(spec.checkpoint, spec.seed)
