"""The typed configs of the mixture density baseline (`cvmdx_jax.models.mdn`,
`cvmdx_jax.train.mdn`, configs/mdn.py): the network, the loss section and the run.

A run stores its `MDNRunConfig` as `config.json` (`runs.layout`) with `model.num_tokens`
set from the tokens it was trained on; `inference.mdn_baseline.load_mdn` rebuilds it
from there.
"""

import dataclasses
from typing import Any

from cvmdx_jax.config.fields import NON_NEGATIVE, POSITIVE, check_ranges, to_dataclass
from cvmdx_jax.config.models import MultipleChoiceConfig
from cvmdx_jax.config.runs import BaselineRunConfig
from cvmdx_jax.config.train import BaselineTrainConfig


@dataclasses.dataclass(frozen=True)
class MixtureDensityConfig(MultipleChoiceConfig):
  """`MultipleChoiceConfig` (trunk, K, the means' control scale and residual base) plus:

  Attributes:
    std_floor_m: m, the smallest standard deviation of a position coordinate.
  """

  std_floor_m: float = 0.05

  def __post_init__(self):
    super().__post_init__()
    check_ranges(self, {"std_floor_m": POSITIVE})


@dataclasses.dataclass(frozen=True)
class MDNLossConfig:
  """The `loss` section: the winner-takes-all warm-up before the mixture NLL.

  Attributes:
    warmup_epochs: epochs whose loss is the multiple-choice MLP's (the winner's ADE plus
      `cls_weight` x the mode cross-entropy) with the winner's Gaussian NLL for the stds
      (0: the mixture NLL from the first step).
    cls_weight: weight of the cross-entropy in the warm-up.
  """

  warmup_epochs: int = 0
  cls_weight: float = 1.0

  def __post_init__(self):
    check_ranges(self, {"warmup_epochs": NON_NEGATIVE, "cls_weight": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class MDNRunConfig(BaselineRunConfig):
  """A mixture density baseline run: `BaselineRunConfig`'s data, tokens, seed and `train`
  section (its `select_metric` "loss" is the val mixture NLL), with the model a
  `MixtureDensityConfig` and the loss an `MDNLossConfig`."""

  model: MixtureDensityConfig = MixtureDensityConfig(num_tokens=0)
  loss: MDNLossConfig = MDNLossConfig()
  train: BaselineTrainConfig = BaselineTrainConfig(select_metric="loss")

  @classmethod
  def from_config(cls, config: Any) -> "MDNRunConfig":
    """The typed run config of a configs/mdn.py ConfigDict (or of a run's config.json);
    ConfigFieldError or ValueError naming the field when one is bad."""
    sections = dict(config.items())
    model = dict(sections.pop("model").items())
    model.setdefault("num_tokens", 0)
    return to_dataclass(
        cls, sections, model=to_dataclass(MixtureDensityConfig, model, where="model")
    )
