"""IL: imitation learning alone, Table I's "IL" row.

The LSTM A3C network trained only by imitation, no reward. By default (il_expert=on_policy) the
agents walk with their own policy and learn the BFS-optimal actions of every state they visit
(DAgger's labels); il_expert=walk_back is the paper's expert (one 20-step walk back from each
destination, reversed), il_expert=shortest one BFS-optimal path per target. Frames count the steps
trained on.

    kgnavbench train --method imitation --frames 1000000
    kgnavbench eval --method imitation --run runs/train/imitation-...
"""

from dataclasses import dataclass

from kgnavbench.models import ModelConfig
from kgnavbench.train import TrainOptions, learn, load_policy

DESCRIPTION = "imitation learning only: the expert's actions, no reward (LSTM network)"


@dataclass
class Config(TrainOptions):
    il: bool = True


def model_config(config: Config) -> ModelConfig:
    return ModelConfig(arch="lstm", kg="none", hidden=config.hidden, lstm=config.lstm, pixels=config.pixels)


def train(config: Config, run) -> None:
    learn(run, config, model_config(config), rl=False)


def make_policy(config: Config, spec):
    return load_policy(spec.checkpoint, spec.seed)
