"""IL: imitation learning alone, Table I's "IL" row.

The LSTM A3C network trained only by imitation, no reward. By default (il_expert=walk_back) it is the
paper's IL: "only one expert trajectory for each training target", walked back from the destination
with MoveBack, else MoveLeft, else RotateRight for 10..il_walk steps, then reversed. il_expert=dagger
is ours, not the paper's: the agents walk with their own policy and learn the BFS-optimal actions of
every state they visit (DAgger with a privileged shortest-path teacher; Table I's extra row "IL, DAgger
with a shortest-path teacher"); il_expert=shortest is one BFS-optimal path per target. Frames count
the steps trained on (with dagger: the steps walked).

    kgnavbench train --method imitation --frames 1000000
    kgnavbench eval --method imitation --run runs/train/imitation-...
"""

from dataclasses import dataclass

from kgnavbench.models import ModelConfig
from kgnavbench.policy import load_policy
from kgnavbench.runs import TrainOptions
from kgnavbench.train import learn

DESCRIPTION = "imitation learning only: the expert's actions, no reward (LSTM network)"


@dataclass
class Config(TrainOptions):
    il: bool = True


def model_config(config: Config) -> ModelConfig:
    return ModelConfig(arch="lstm", kg="none", hidden=config.hidden, lstm=config.lstm, pixels=config.pixels)


def train(config: Config, run) -> None:
    learn(run, config, model_config(config), rl=False)


def make_policy(config: Config, spec):
    return load_policy(spec.checkpoint, spec.seed, spec.device)
