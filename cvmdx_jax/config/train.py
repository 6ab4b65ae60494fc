"""The `train` sections of the trainers: batch, epochs, optimiser, checkpoints."""

import dataclasses
from typing import ClassVar

from cvmdx_jax.config.fields import (
    BELOW_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    ConfigFieldError,
    check_ranges,
)


@dataclasses.dataclass(frozen=True)
class BaseTrainConfig:
  """What every `train` section holds: batch, epochs, learning rate, gradient clipping,
  checkpoints; each trainer's section extends it."""

  batch_size: int = 64
  num_epochs: int = 100
  learning_rate: float = 5e-4
  grad_clip: float = 1.0
  checkpoint_every: int = 5
  keep: int = 2

  RANGES: ClassVar = {
      "batch_size": POSITIVE,
      "num_epochs": POSITIVE,
      "learning_rate": POSITIVE,
      "grad_clip": NON_NEGATIVE,
      "checkpoint_every": POSITIVE,
      "keep": POSITIVE,
  }

  def __post_init__(self):
    check_ranges(self, self.RANGES)


@dataclasses.dataclass(frozen=True)
class TokenizerTrainConfig(BaseTrainConfig):
  """The `train` section of the tokeniser: Adam with clipping (configs/tokenizer.py
  documents the fields)."""


@dataclasses.dataclass(frozen=True)
class DiffusionTrainConfig(BaseTrainConfig):
  """The `train` section of the denoiser: `BaseTrainConfig` plus the AdamW schedule and the
  EMA (configs/diffusion.py documents the fields); batch and peak learning rate the
  paper's."""

  batch_size: int = 256
  learning_rate: float = 2e-4
  warmup_steps: int = 3000
  min_lr: float = 1e-6
  weight_decay: float = 0.0
  ema_decay: float = 0.9999

  RANGES: ClassVar = {
      **BaseTrainConfig.RANGES,
      "warmup_steps": NON_NEGATIVE,
      "min_lr": NON_NEGATIVE,
      "weight_decay": NON_NEGATIVE,
      "ema_decay": BELOW_ONE,
  }


@dataclasses.dataclass(frozen=True)
class DistillTrainConfig(DiffusionTrainConfig):
  """The `train` section of a distillation stage: `DiffusionTrainConfig` with a shorter,
  gentler schedule from a trained teacher (configs/distill.py documents the fields)."""

  num_epochs: int = 20
  learning_rate: float = 1e-4
  warmup_steps: int = 100
  ema_decay: float = 0.999


# val read-outs of the baseline's `train.baseline.evaluate` the epoch can be chosen on
# (lower is better)
SELECT_METRICS = (
    "loss",
    "wta_ade",
    "min_ade",
    "min_fde",
    "ml_ade",
    "ml_fde",
    "mean_ade",
    "mean_fde",
)


@dataclasses.dataclass(frozen=True)
class BaselineTrainConfig(BaseTrainConfig):
  """The `train` section of the multiple-choice baseline: `BaseTrainConfig` plus the AdamW
  schedule and the val read-out that picks the epoch (configs/baseline.py documents the
  fields)."""

  batch_size: int = 256
  num_epochs: int = 30
  learning_rate: float = 2e-3
  checkpoint_every: int = 10
  keep: int = 1
  warmup_steps: int = 100
  end_lr_fraction: float = 0.01
  weight_decay: float = 1e-4
  select_metric: str = "min_ade"

  RANGES: ClassVar = {
      **BaseTrainConfig.RANGES,
      "warmup_steps": NON_NEGATIVE,
      "end_lr_fraction": FRACTION,
      "weight_decay": NON_NEGATIVE,
  }

  def __post_init__(self):
    super().__post_init__()
    if self.select_metric not in SELECT_METRICS:
      raise ConfigFieldError(
          "select_metric", self.select_metric, f"must be one of {SELECT_METRICS}"
      )
