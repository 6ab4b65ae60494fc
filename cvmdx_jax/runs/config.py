"""The typed configs of the trainers, built and checked once at the entry point.

    config = DiffusionConfig.from_config(configs.diffusion.get_config("demo"))

`from_config` turns a ConfigDict of configs/tokenizer.py, configs/diffusion.py or
configs/baseline.py into a
frozen dataclass (`config_dataclass.to_dataclass`); every field's range is checked by the
dataclass that holds it (`ConfigFieldError` names the dotted field, e.g.
"diffusion.class_weights"). Below the entry points only these dataclasses travel.
A diffusion run stores its `DiffusionConfig` as `config.json` (`runs.layout`), with
`model.num_tokens` set from the tokens it was trained on; so does a baseline run its
`BaselineConfig`.
"""

import dataclasses
from typing import Any, ClassVar

from cvmdx_jax.config_dataclass import (BELOW_ONE, FRACTION, NON_NEGATIVE, POSITIVE, SEED,
                                        ConfigFieldError, Range, check_ranges, to_dataclass)
from cvmdx_jax.inference.sampling import SamplingConfig
from cvmdx_jax.models import quantizer as quantizer_lib
from cvmdx_jax.models.multiple_choice import MultipleChoiceConfig
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models.scenario_encoder import EncoderConfig
from cvmdx_jax.models.unet1d import UNetConfig
from cvmdx_jax.targets import DenoiserConfig


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """The `train` section of the tokeniser: batch, epochs, Adam learning rate, clipping,
  checkpoints (configs/tokenizer.py documents the fields)."""

  batch_size: int = 64
  num_epochs: int = 100
  learning_rate: float = 5e-4
  grad_clip: float = 1.0
  checkpoint_every: int = 5
  keep: int = 2

  RANGES: ClassVar = {"batch_size": POSITIVE, "num_epochs": POSITIVE,
                      "learning_rate": POSITIVE, "grad_clip": NON_NEGATIVE,
                      "checkpoint_every": POSITIVE, "keep": POSITIVE}

  def __post_init__(self):
    check_ranges(self, self.RANGES)


@dataclasses.dataclass(frozen=True)
class DiffusionTrainConfig(TrainConfig):
  """The `train` section of the denoiser: `TrainConfig` plus the AdamW schedule and the EMA
  (configs/diffusion.py documents the fields)."""

  batch_size: int = 256
  warmup_steps: int = 3000
  min_lr: float = 1e-6
  weight_decay: float = 0.0
  ema_decay: float = 0.9999

  RANGES: ClassVar = {**TrainConfig.RANGES, "warmup_steps": NON_NEGATIVE,
                      "min_lr": NON_NEGATIVE, "weight_decay": NON_NEGATIVE,
                      "ema_decay": BELOW_ONE}


@dataclasses.dataclass(frozen=True)
class UncertaintyConfig:
  """The `uncertainty` section: shrinkage and ridge of the per-entry Gaussians of delta."""

  shrinkage: float = 16.0
  ridge: float = 1e-3

  def __post_init__(self):
    check_ranges(self, {"shrinkage": NON_NEGATIVE, "ridge": NON_NEGATIVE})


def _check_run(config) -> None:
  check_ranges(config, {"seed": SEED})


@dataclasses.dataclass(frozen=True)
class TokenizerRunConfig:
  """A tokeniser run (configs/tokenizer.py); `model` is the model's `TokenizerConfig`, its
  quantiser built from the config's `quantizer` section (latent_dim = the encoder's)."""

  data_dir: str = "data/sumo"
  splits: tuple[str, ...] = ()
  seed: int = 0
  encode_batch: int = 512
  model: tokenizer_lib.TokenizerConfig = tokenizer_lib.TokenizerConfig()
  uncertainty: UncertaintyConfig = UncertaintyConfig()
  train: TrainConfig = TrainConfig()

  def __post_init__(self):
    _check_run(self)
    check_ranges(self, {"encode_batch": POSITIVE})

  @classmethod
  def from_config(cls, config: Any) -> "TokenizerRunConfig":
    """The typed run config of a configs/tokenizer.py ConfigDict (ConfigFieldError or
    ValueError naming the field when one is out of range)."""
    sections = dict(config.items())
    encoder = to_dataclass(EncoderConfig, config.model.encoder, where="model.encoder")
    quantizer = to_dataclass(quantizer_lib.QuantizerConfig, sections.pop("quantizer"),
                             where="quantizer", latent_dim=encoder.latent_dim)
    model = to_dataclass(tokenizer_lib.TokenizerConfig, sections.pop("model"), where="model",
                         encoder=encoder, quantizer=quantizer)
    return to_dataclass(cls, sections, model=model)


@dataclasses.dataclass(frozen=True)
class DiffusionConfig:
  """A diffusion run (configs/diffusion.py).

  Attributes:
    data_dir: the dataset directory.
    tokenizer_dir: the tokeniser run whose tokens condition the denoiser.
    seed: init, example order and step keys.
    model: the U-Net; `num_tokens` is 0 until the trainer sets it to the tokens' Q
      (`with_tokens`), `cond_dim` follows `diffusion.conditioning`, `num_intents` and
      `intent_features` `diffusion.intent_conditioning`.
    diffusion: the denoiser's `targets.DenoiserConfig`.
    train: `DiffusionTrainConfig`.
    sampling: the run's default `SamplingConfig`.
  """

  data_dir: str = "data/sumo"
  tokenizer_dir: str = "runs/tokenizer"
  seed: int = 0
  model: UNetConfig = UNetConfig(num_tokens=0)
  diffusion: DenoiserConfig = DenoiserConfig()
  train: DiffusionTrainConfig = DiffusionTrainConfig()
  sampling: SamplingConfig = SamplingConfig()

  def __post_init__(self):
    _check_run(self)
    cond_dim = self.diffusion.cond_dim
    if self.model.cond_dim != cond_dim:
      raise ValueError(f"model.cond_dim={self.model.cond_dim}: the {self.diffusion.conditioning!r} "
                       f"conditioning has {cond_dim - self.diffusion.guidance_input} ego-motion "
                       "features (cvmdx_jax/ego_motion.py, FEATURES)"
                       f"{' and the guidance weight' if self.diffusion.guidance_input else ''}")
    d = self.diffusion
    if (self.model.num_intents, self.model.intent_features) != (d.num_intents,
                                                                d.intent_features):
      raise ValueError(f"model.num_intents={self.model.num_intents}, model.intent_features="
                       f"{self.model.intent_features}: diffusion.intent_conditioning="
                       f"{d.intent_conditioning} needs {d.num_intents}, {d.intent_features}")

  @classmethod
  def from_config(cls, config: Any) -> "DiffusionConfig":
    """The typed run config of a configs/diffusion.py ConfigDict (or of a run's
    config.json); ConfigFieldError or ValueError naming the field when one is bad."""
    sections = dict(config.items())
    diffusion = to_dataclass(DenoiserConfig, sections.pop("diffusion"), where="diffusion")
    model = dict(sections.pop("model").items())
    model.setdefault("num_tokens", 0)
    model.setdefault("cond_dim", diffusion.cond_dim)
    model.setdefault("num_intents", diffusion.num_intents)
    model.setdefault("intent_features", diffusion.intent_features)
    return to_dataclass(cls, sections, diffusion=diffusion,
                        model=to_dataclass(UNetConfig, model, where="model"))

  def with_tokens(self, num_tokens: int) -> "DiffusionConfig":
    """This config with the U-Net sized for `num_tokens` tokens (Q; token Q is null)."""
    return dataclasses.replace(self, model=dataclasses.replace(self.model,
                                                               num_tokens=num_tokens))


# DistillConfig.teacher_substeps: k teacher steps a student step
_SUBSTEPS = Range("an integer >= 2", lambda v: v >= 2 and v == int(v))


@dataclasses.dataclass(frozen=True)
class DistillConfig:
  """A distillation run (configs/distill.py, `cvmdx_jax.train.distill`): one stage from a
  teacher run. A guided denoiser teaches a guidance student (w as an input), or with
  `guided_progressive` a progressive student for `steps` steps directly; a guidance or
  progressive student teaches a progressive student for `steps` steps (itself sampled at
  `teacher_substeps` x `steps`).

  Attributes:
    teacher_dir: the teacher run (a diffusion run or a distillation run).
    data_dir, tokenizer_dir: the teacher's training data and tokeniser run ("" = the paths
      in the teacher's config.json).
    seed: the noise, timesteps, example order and (guidance stage) the new FiLM layer.
    steps: S, the student's sampling steps (`sampling.sampler` "distilled").
    guided_progressive: with a guided denoiser as teacher, the student regresses k DDIM
      steps of the guided pair on the grid of k S (guidance and progressive distillation
      in one run) instead of the guided v at every t.
    teacher_substeps: k, the teacher's DDIM steps per student step of a progressive stage
      (2: Salimans & Ho's halving; a progressive teacher must sample k S steps).
    train: `DiffusionTrainConfig` (AdamW, EMA, epochs over the train split).
  """

  teacher_dir: str = "runs/diffusion"
  data_dir: str = ""
  tokenizer_dir: str = ""
  seed: int = 0
  steps: int = 2
  guided_progressive: bool = False
  teacher_substeps: int = 2
  train: DiffusionTrainConfig = DiffusionTrainConfig()

  def __post_init__(self):
    _check_run(self)
    check_ranges(self, {"steps": POSITIVE, "teacher_substeps": _SUBSTEPS})

  @classmethod
  def from_config(cls, config: Any) -> "DistillConfig":
    """The typed run config of a configs/distill.py ConfigDict."""
    return to_dataclass(cls, config)


# val read-outs of the baseline's `train.baseline.evaluate` the epoch can be chosen on
# (lower is better)
SELECT_METRICS = ("loss", "wta_ade", "min_ade", "min_fde", "ml_ade", "ml_fde", "mean_ade",
                  "mean_fde")


@dataclasses.dataclass(frozen=True)
class BaselineTrainConfig(TrainConfig):
  """The `train` section of the multiple-choice baseline: `TrainConfig` plus the AdamW
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

  RANGES: ClassVar = {**TrainConfig.RANGES, "warmup_steps": NON_NEGATIVE,
                      "end_lr_fraction": FRACTION, "weight_decay": NON_NEGATIVE}

  def __post_init__(self):
    super().__post_init__()
    if self.select_metric not in SELECT_METRICS:
      raise ConfigFieldError("select_metric", self.select_metric,
                             f"must be one of {SELECT_METRICS}")


@dataclasses.dataclass(frozen=True)
class WTALossConfig:
  """The `loss` section of the baseline: weight of the mode cross-entropy beside the
  winner's ADE (m)."""

  cls_weight: float = 1.0

  def __post_init__(self):
    check_ranges(self, {"cls_weight": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
  """A multiple-choice baseline run (configs/baseline.py, `cvmdx_jax.train.baseline`).

  Attributes:
    data_dir: the dataset directory.
    tokenizer_dir: the tokeniser run whose tokens q and delta it reads.
    seed: init and example order.
    model: the MLP; `num_tokens` is 0 until the trainer sets it to the tokens' Q
      (`with_tokens`).
    loss: `WTALossConfig`.
    train: `BaselineTrainConfig`.
  """

  data_dir: str = "data/sumo"
  tokenizer_dir: str = "runs/tokenizer"
  seed: int = 0
  model: MultipleChoiceConfig = MultipleChoiceConfig(num_tokens=0)
  loss: WTALossConfig = WTALossConfig()
  train: BaselineTrainConfig = BaselineTrainConfig()

  def __post_init__(self):
    _check_run(self)

  @classmethod
  def from_config(cls, config: Any) -> "BaselineConfig":
    """The typed run config of a configs/baseline.py ConfigDict (or of a run's
    config.json); ConfigFieldError or ValueError naming the field when one is bad."""
    sections = dict(config.items())
    model = dict(sections.pop("model").items())
    model.setdefault("num_tokens", 0)
    return to_dataclass(cls, sections, model=to_dataclass(MultipleChoiceConfig, model,
                                                          where="model"))

  def with_tokens(self, num_tokens: int) -> "BaselineConfig":
    """This config with the MLP's token embedding sized for `num_tokens` tokens (Q)."""
    return dataclasses.replace(self, model=dataclasses.replace(self.model,
                                                               num_tokens=num_tokens))
