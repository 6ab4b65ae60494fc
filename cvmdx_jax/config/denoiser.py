"""What a trained denoiser is: `DenoiserConfig`, stored with it (config.json, section
`diffusion`); the control normalisation it implies is `cvmdx_jax.targets`."""

import dataclasses
from typing import ClassVar

from cvmdx_jax import constants, ego_motion
from cvmdx_jax.config.fields import (
    AT_LEAST_TWO,
    BELOW_ONE,
    POSITIVE,
    ConfigFieldError,
    check_ranges,
)

PAPER_SCALE = (constants.ACCEL_SCALE, constants.YAW_RATE_SCALE)


@dataclasses.dataclass(frozen=True)
class DenoiserConfig:
  """The `diffusion` section of a diffusion run (configs/diffusion.py documents the fields).

  Attributes:
    num_steps: T of the cosine schedule.
    cond_drop_prob: probability of dropping the token in training (CFG).
    control_scale: (m/s^2, rad/s) per normalised unit of [a_x, yaw_rate].
    conditioning: one of `ego_motion.CONDITIONINGS`.
    residual_decay_s: (a_x, yaw rate) decay time constants of the residual base, s.
    class_weights: loss weight per maneuver class (keep lane, lcr, lcl).
    guidance_input: the U-Net's last FiLM feature is the guidance weight w: a
      guidance-distilled student (`diffusion.distillation`), one evaluation per step in
      place of the guided pair (beyond the paper).
    intent_conditioning: the U-Net also sees the maneuver class (one-hot keep lane, lcr,
      lcl after the ego features): the true one in training, one drawn per sample from
      its intent classifier on the ego features (`UNet1D.intent_logits`, trained beside it
      by cross-entropy) in sampling (beyond the paper). Needs an `ego_film*` conditioning.
  """

  num_steps: int = 1000
  cond_drop_prob: float = 0.1
  control_scale: tuple[float, float] = PAPER_SCALE
  conditioning: str = "token"
  residual_decay_s: tuple[float, float] = (3.0, 0.1)
  class_weights: tuple[float, ...] = (1.0,) * constants.NUM_CLASSES
  guidance_input: bool = False
  intent_conditioning: bool = False

  RANGES: ClassVar = {
      "num_steps": AT_LEAST_TWO,
      "cond_drop_prob": BELOW_ONE,
      "control_scale": POSITIVE,
      "residual_decay_s": POSITIVE,
      "class_weights": POSITIVE,
  }

  def __post_init__(self):
    check_ranges(self, self.RANGES)
    if len(self.class_weights) != constants.NUM_CLASSES:
      raise ConfigFieldError(
          "class_weights",
          self.class_weights,
          f"need {constants.NUM_CLASSES} positive finite weights, one per "
          f"class {constants.CLASS_NAMES}",
      )
    ego_motion.check_conditioning(self.conditioning)
    if self.intent_conditioning and not ego_motion.uses_film(self.conditioning):
      raise ConfigFieldError(
          "intent_conditioning",
          self.intent_conditioning,
          "the intent classifier reads the ego features: needs an "
          f"ego_film* conditioning, not {self.conditioning!r}",
      )

  @property
  def cond_dim(self) -> int:
    """Width of the U-Net's FiLM conditioning vector: the ego-motion features of an
    `ego_film*` conditioning, then the one-hot maneuver class of an intent conditioning,
    then w for a guidance student."""
    film = ego_motion.NUM_FEATURES if ego_motion.uses_film(self.conditioning) else 0
    return film + self.num_intents + int(self.guidance_input)

  @property
  def num_intents(self) -> int:
    """Classes of the U-Net's intent classifier: the maneuver classes where the intent
    conditioning is on, else 0."""
    return constants.NUM_CLASSES if self.intent_conditioning else 0

  @property
  def intent_features(self) -> int:
    """Input width of the intent classifier: the ego features, where it is on."""
    return ego_motion.NUM_FEATURES if self.intent_conditioning else 0

  @property
  def weighted_classes(self) -> bool:
    """Whether the loss weighs the classes unequally (beyond the paper)."""
    return any(w != 1.0 for w in self.class_weights)
