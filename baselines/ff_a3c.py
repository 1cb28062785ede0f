"""FF A3C (Zhu et al. 2017): the feed-forward target-driven actor-critic the paper compares with.

The last 4 frames' features and the target image's, the siamese and fusion layers, then a
scene-specific layer with policy and value heads per training kitchen. Its heads exist only for the
training kitchens, so (as in the paper) it has no row for unseen kitchens; evaluated there it uses the
first kitchen's heads.

    kgnavbench train --method ff_a3c --frames 2000000
    kgnavbench eval --method ff_a3c --run runs/train/ff_a3c-...
"""

from dataclasses import dataclass

from kgnavbench.models import ModelConfig
from kgnavbench.policy import load_policy
from kgnavbench.runs import TrainOptions
from kgnavbench.train import learn

DESCRIPTION = "feed-forward A3C of Zhu et al. 2017: 4 stacked frames, scene-specific heads"


@dataclass
class Config(TrainOptions):
    history: int = 4  # frames stacked


def model_config(config: Config) -> ModelConfig:
    return ModelConfig(
        arch="ff", kg="none", hidden=config.hidden, history=config.history, pixels=config.pixels
    )


def train(config: Config, run) -> None:
    learn(run, config, model_config(config))


def make_policy(config: Config, spec):
    return load_policy(spec.checkpoint, spec.seed, spec.device)
