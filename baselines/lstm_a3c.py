"""LSTM A3C: the paper's recurrent actor-critic, with its two training aids as options.

Table I's rows "LSTM A3C" (no options), "+IL" (il=true), "+TSE" (tse=true) and "+IL+TSE", and the
control row of the graph, "+IL+TSE, object detections, no graph" (detections=true). The network
(kgnavbench.models): the siamese layer over the frozen encoder's features of the view and of the target
image, the fusion layer, an LSTM, policy and value heads. Training (kgnavbench.train): a synchronous
batched A2C over all training kitchens' seen targets; `il` mixes in cross-entropy on expert
trajectories, `tse` adds relabelled sub-trajectories of the agent's own episodes.

    kgnavbench train --method lstm_a3c --set il=true --set tse=true --frames 3000000
    kgnavbench eval --method lstm_a3c --set il=true --set tse=true --run runs/train/lstm_a3c-...

Every training option (learning rate, agents, rollout length, ...) is a field of TrainOptions.
"""

from dataclasses import dataclass

from kgnavbench.models import ModelConfig
from kgnavbench.policy import load_policy
from kgnavbench.runs import TrainOptions
from kgnavbench.train import learn

DESCRIPTION = "LSTM A3C over frozen view features (options il, tse: the paper's +IL, +TSE rows)"


@dataclass
class Config(TrainOptions):
    # il and tse are TrainOptions fields, off by default.
    # the graph's control row "+IL+TSE, object detections, no graph": the network also receives the
    # visible-type vectors R_t and R_g that the KG rows see, through one layer, with no GCN
    detections: bool = False


def model_config(config: Config) -> ModelConfig:
    return ModelConfig(
        arch="lstm",
        kg="none",
        hidden=config.hidden,
        lstm=config.lstm,
        pixels=config.pixels,
        detections=config.detections,
    )


def train(config: Config, run) -> None:
    learn(run, config, model_config(config))


def make_policy(config: Config, spec):
    return load_policy(spec.checkpoint, spec.seed, spec.device)
