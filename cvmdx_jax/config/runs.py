"""The typed run configs of the trainers, built and checked once at the entry point.

    config = DiffusionRunConfig.from_config(configs.diffusion.get_config("demo"))

`from_config` turns a ConfigDict of configs/tokenizer.py, configs/diffusion.py,
configs/distill.py or configs/baseline.py into a frozen dataclass (`fields.to_dataclass`);
every field's range is checked by the dataclass that holds it (`ConfigFieldError` names the
dotted field, e.g. "diffusion.class_weights"). Below the entry points only these
dataclasses travel. A diffusion run stores its `DiffusionRunConfig` as `config.json`
(`runs.layout`), with `model.num_tokens` set from the tokens it was trained on; so does a
baseline run its `BaselineRunConfig`.
"""

import dataclasses
from typing import Any

from cvmdx_jax.config.denoiser import DenoiserConfig
from cvmdx_jax.config.fields import NON_NEGATIVE, POSITIVE, SEED, Range, check_ranges, to_dataclass
from cvmdx_jax.config.models import (
    EncoderConfig,
    MultipleChoiceConfig,
    QuantizerConfig,
    TokenizerConfig,
    UNetConfig,
)
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.config.train import (
    BaselineTrainConfig,
    DiffusionTrainConfig,
    DistillTrainConfig,
    TokenizerTrainConfig,
)
from cvmdx_jax.errors import UserError


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
  model: TokenizerConfig = TokenizerConfig()
  uncertainty: UncertaintyConfig = UncertaintyConfig()
  train: TokenizerTrainConfig = TokenizerTrainConfig()

  def __post_init__(self):
    _check_run(self)
    check_ranges(self, {"encode_batch": POSITIVE})

  @classmethod
  def from_config(cls, config: Any) -> "TokenizerRunConfig":
    """The typed run config of a configs/tokenizer.py ConfigDict (ConfigFieldError or
    ValueError naming the field when one is out of range)."""
    sections = dict(config.items())
    encoder = to_dataclass(EncoderConfig, config.model.encoder, where="model.encoder")
    quantizer = to_dataclass(
        QuantizerConfig, sections.pop("quantizer"), where="quantizer", latent_dim=encoder.latent_dim
    )
    model = to_dataclass(
        TokenizerConfig, sections.pop("model"), where="model", encoder=encoder, quantizer=quantizer
    )
    return to_dataclass(cls, sections, model=model)


@dataclasses.dataclass(frozen=True)
class DiffusionRunConfig:
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
      raise UserError(
          f"model.cond_dim={self.model.cond_dim}: the {self.diffusion.conditioning!r} "
          f"conditioning has {cond_dim - self.diffusion.guidance_input} ego-motion "
          "features (cvmdx_jax/ego_motion.py, FEATURES)"
          f"{' and the guidance weight' if self.diffusion.guidance_input else ''}"
      )
    d = self.diffusion
    if (self.model.num_intents, self.model.intent_features) != (d.num_intents, d.intent_features):
      raise UserError(
          f"model.num_intents={self.model.num_intents}, model.intent_features="
          f"{self.model.intent_features}: diffusion.intent_conditioning="
          f"{d.intent_conditioning} needs {d.num_intents}, {d.intent_features}"
      )

  @classmethod
  def from_config(cls, config: Any) -> "DiffusionRunConfig":
    """The typed run config of a configs/diffusion.py ConfigDict (or of a run's
    config.json); ConfigFieldError or ValueError naming the field when one is bad."""
    sections = dict(config.items())
    diffusion = to_dataclass(DenoiserConfig, sections.pop("diffusion"), where="diffusion")
    model = dict(sections.pop("model").items())
    model.setdefault("num_tokens", 0)
    model.setdefault("cond_dim", diffusion.cond_dim)
    model.setdefault("num_intents", diffusion.num_intents)
    model.setdefault("intent_features", diffusion.intent_features)
    return to_dataclass(
        cls, sections, diffusion=diffusion, model=to_dataclass(UNetConfig, model, where="model")
    )

  def with_tokens(self, num_tokens: int) -> "DiffusionRunConfig":
    """This config with the U-Net sized for `num_tokens` tokens (Q; token Q is null)."""
    return dataclasses.replace(self, model=dataclasses.replace(self.model, num_tokens=num_tokens))


# DistillRunConfig.teacher_substeps: k teacher steps a student step
_SUBSTEPS = Range("an integer >= 2", lambda v: v >= 2 and v == int(v))


@dataclasses.dataclass(frozen=True)
class DistillRunConfig:
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
    init_dir: a distilled run of the same U-Net whose parameters start the student ("" =
      the teacher's, with a zero row for w); e.g. a 2-step student starting a 1-step one
      that regresses the guided teacher's DDIM-10 itself.
    train: `DistillTrainConfig` (AdamW, EMA, epochs over the train split).
  """

  teacher_dir: str = "runs/diffusion"
  data_dir: str = ""
  tokenizer_dir: str = ""
  seed: int = 0
  steps: int = 4
  guided_progressive: bool = False
  teacher_substeps: int = 2
  init_dir: str = ""
  train: DistillTrainConfig = DistillTrainConfig()

  def __post_init__(self):
    _check_run(self)
    check_ranges(self, {"steps": POSITIVE, "teacher_substeps": _SUBSTEPS})

  @classmethod
  def from_config(cls, config: Any) -> "DistillRunConfig":
    """The typed run config of a configs/distill.py ConfigDict."""
    return to_dataclass(cls, config)


@dataclasses.dataclass(frozen=True)
class WTALossConfig:
  """The `loss` section of the baseline: weight of the mode cross-entropy beside the
  winner's ADE (m)."""

  cls_weight: float = 1.0

  def __post_init__(self):
    check_ranges(self, {"cls_weight": NON_NEGATIVE})


@dataclasses.dataclass(frozen=True)
class BaselineRunConfig:
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
  def from_config(cls, config: Any) -> "BaselineRunConfig":
    """The typed run config of a configs/baseline.py ConfigDict (or of a run's
    config.json); ConfigFieldError or ValueError naming the field when one is bad."""
    sections = dict(config.items())
    model = dict(sections.pop("model").items())
    model.setdefault("num_tokens", 0)
    return to_dataclass(
        cls, sections, model=to_dataclass(MultipleChoiceConfig, model, where="model")
    )

  def with_tokens(self, num_tokens: int) -> "BaselineRunConfig":
    """This config with the MLP's token embedding sized for `num_tokens` tokens (Q)."""
    return dataclasses.replace(self, model=dataclasses.replace(self.model, num_tokens=num_tokens))
