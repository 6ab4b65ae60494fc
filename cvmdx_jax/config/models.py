"""The static settings of the networks: the tokeniser (encoder, quantiser, whole), the
denoiser's U-Net and the learned baseline's multiple-choice MLP."""

import dataclasses
import math

from cvmdx_jax import constants, ego_motion
from cvmdx_jax.config.fields import (
    BELOW_ONE,
    FRACTION,
    NON_NEGATIVE,
    POSITIVE,
    ConfigFieldError,
    check_ranges,
)
from cvmdx_jax.errors import UserError


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
  """Static sizes of E and D.

  Attributes:
    latent_dim: size D of z_hat.
    channels: convolution widths per level (one stride-2 level each).
    kernel_size: temporal kernel of every convolution.
  """

  latent_dim: int = 16
  channels: tuple[int, ...] = (64, 128, 128)
  kernel_size: int = 5

  def __post_init__(self):
    check_ranges(self, {"latent_dim": POSITIVE, "channels": POSITIVE, "kernel_size": POSITIVE})

  def bottleneck_steps(self) -> int:
    """Steps left after the stride-2 levels (75 -> 10 for three levels)."""
    steps = constants.T_OBS
    for _ in self.channels:
      steps = math.ceil(steps / 2)
    return steps


QUANTIZERS = ("vq", "cvq")


@dataclasses.dataclass(frozen=True)
class QuantizerConfig:
  """Static settings of the quantiser.

  Attributes:
    kind: "vq" (plain VQ-VAE) or "cvq" (online clustered codebook).
    codebook_size: Q, number of entries.
    latent_dim: D, size of each entry.
    beta: commitment weight.
    usage_decay: gamma of the running usage average (CVQ).
    revive_strength: how fast alpha_k falls with usage (the 10 of Zheng & Vedaldi).
  """

  kind: str = "cvq"
  codebook_size: int = 60
  latent_dim: int = 16
  beta: float = 0.25
  usage_decay: float = 0.99
  revive_strength: float = 10.0

  def __post_init__(self):
    if self.kind not in QUANTIZERS:
      raise UserError(f"quantizer kind '{self.kind}' is not one of {QUANTIZERS}")
    check_ranges(
        self,
        {
            "codebook_size": POSITIVE,
            "latent_dim": POSITIVE,
            "beta": NON_NEGATIVE,
            "usage_decay": FRACTION,
            "revive_strength": NON_NEGATIVE,
        },
    )


@dataclasses.dataclass(frozen=True)
class TokenizerConfig:
  """Static settings of the tokeniser.

  Attributes:
    encoder: sizes of E and D.
    quantizer: codebook settings; its latent_dim must equal encoder.latent_dim.
    cls_weight: lambda, weight of the maneuver cross-entropy.
    ego_weight: weight of the ego vehicle's features in the reconstruction error (each
      neighbour has weight 1).
  """

  encoder: EncoderConfig = EncoderConfig()
  quantizer: QuantizerConfig = QuantizerConfig()
  cls_weight: float = 1.0
  ego_weight: float = 1.0

  def __post_init__(self):
    check_ranges(self, {"cls_weight": NON_NEGATIVE, "ego_weight": NON_NEGATIVE})
    if self.encoder.latent_dim != self.quantizer.latent_dim:
      raise UserError(
          f"encoder latent_dim {self.encoder.latent_dim} != quantizer "
          f"latent_dim {self.quantizer.latent_dim}"
      )


@dataclasses.dataclass(frozen=True)
class UNetConfig:
  """Static U-Net sizes.

  Attributes:
    num_tokens: Q, the codebook size; token Q is the null token.
    base_channels: channels at the finest level.
    channel_mult: per-level channel multipliers (the sequence halves per level).
    num_res_blocks: residual blocks per level on the way down (one more up).
    emb_mult: timestep/token embedding width = emb_mult * base_channels (reference: 2).
    attention_levels: level indices with self-attention (default: the two coarsest).
    num_heads: attention heads.
    groups: GroupNorm groups.
    dropout: dropout rate inside residual blocks (training only).
    channels: input/output channels (2: a_x, yaw rate).
    length: sequence length (125).
    padded_length: length the sequence is zero-padded to (divisible by 2^(levels-1)),
      (padded_length - length) // 2 zeros on the left, the rest on the right.
    cond_dim: width of the optional conditioning vector (0 = token only, the paper).
    cond_hidden: widths of the hidden layers (SiLU) of the conditioning vector's MLP,
      which ends in the embedding width; () = one hidden layer of the embedding width
      (emb_mult * base_channels), as before this field existed.
    num_intents: classes of the intent classifier (`intent_logits`: an MLP with the
      conditioning MLP's hidden widths from the first `intent_features` entries of the
      conditioning vector to logits; beyond the paper); 0 = none.
    intent_features: width of the classifier's input (the ego features).
  """

  num_tokens: int = 60
  base_channels: int = 128
  channel_mult: tuple[int, ...] = (1, 2, 3, 4)
  num_res_blocks: int = 1
  emb_mult: int = 2
  attention_levels: tuple[int, ...] = (2, 3)
  num_heads: int = 4
  groups: int = 32
  dropout: float = 0.0
  channels: int = 2
  length: int = constants.T_PRED
  padded_length: int = 128
  cond_dim: int = 0
  cond_hidden: tuple[int, ...] = ()
  num_intents: int = 0
  intent_features: int = 0

  def __post_init__(self):
    check_ranges(
        self,
        {
            **dict.fromkeys(
                (
                    "base_channels",
                    "channel_mult",
                    "num_res_blocks",
                    "emb_mult",
                    "num_heads",
                    "groups",
                ),
                POSITIVE,
            ),
            "dropout": BELOW_ONE,
            "attention_levels": NON_NEGATIVE,
            "cond_hidden": POSITIVE,
            "num_intents": NON_NEGATIVE,
            "intent_features": NON_NEGATIVE,
        },
    )
    if bool(self.num_intents) != bool(self.intent_features) or (
        self.intent_features > self.cond_dim
    ):
      raise UserError(
          f"num_intents={self.num_intents}, intent_features="
          f"{self.intent_features}: the intent classifier needs both, and reads "
          f"the first intent_features of the cond_dim={self.cond_dim} inputs"
      )
    self._check_levels()
    factor = 2 ** (len(self.channel_mult) - 1)
    if self.padded_length % factor or self.padded_length < self.length:
      raise UserError(
          f"padded_length={self.padded_length} must be >= length={self.length} "
          f"and divisible by {factor}"
      )

  def _check_levels(self) -> None:
    """At least one level; attention only at levels that exist; every level's channels
    split into `groups` groups and each attended level's (and the middle block's, the
    coarsest) into `num_heads` heads."""
    levels = len(self.channel_mult)
    if not levels:
      raise ConfigFieldError("channel_mult", self.channel_mult, "needs at least one level")
    if any(level >= levels for level in self.attention_levels):
      raise ConfigFieldError(
          "attention_levels",
          self.attention_levels,
          f"the levels are 0..{levels - 1} (one per channel_mult entry)",
      )
    widths = [self.base_channels * m for m in self.channel_mult]
    for name, parts, attended in (
        ("groups", self.groups, range(levels)),
        ("num_heads", self.num_heads, {*self.attention_levels, levels - 1}),
    ):
      bad = sorted({widths[level] for level in attended if widths[level] % parts})
      if bad:
        raise ConfigFieldError(
            name,
            parts,
            f"must divide the channels of every level it "
            f"splits (base_channels x channel_mult: {bad})",
        )

  @property
  def null_token(self) -> int:
    return self.num_tokens

  @property
  def cond_widths(self) -> tuple[int, ...]:
    """Hidden widths of the conditioning vector's MLP (`cond_hidden`, or the embedding's)."""
    return self.cond_hidden or (self.emb_mult * self.base_channels,)


@dataclasses.dataclass(frozen=True)
class MultipleChoiceConfig:
  """Static sizes of the multiple-choice MLP.

  Attributes:
    num_tokens: Q, the codebook size of the tokeniser whose tokens it reads (0 in a
      run config until the trainer sets it from the tokens, `BaselineRunConfig.with_tokens`).
    num_hypotheses: K heads (= C_max of cVMDx's hypotheses).
    token_dim: width of the token embedding.
    hidden: widths of the hidden layers (GELU).
    control_scale: [a_x m/s^2, yaw rate rad/s] per unit of a head's output.
    residual_decay_s: (tau_a, tau_r) s of the residual base (`ego_motion.residual_controls`).
  """

  num_tokens: int = 60
  num_hypotheses: int = 3
  token_dim: int = 16
  hidden: tuple[int, ...] = (256, 256)
  control_scale: tuple[float, float] = (4.0, 0.1)
  residual_decay_s: tuple[float, float] = (3.0, 0.1)

  def __post_init__(self):
    check_ranges(
        self,
        {
            "num_tokens": NON_NEGATIVE,
            **dict.fromkeys(
                ("num_hypotheses", "token_dim", "hidden", "control_scale", "residual_decay_s"),
                POSITIVE,
            ),
        },
    )
    if len(self.control_scale) != 2 or len(self.residual_decay_s) != 2:
      raise UserError(
          "control_scale and residual_decay_s need two values (a_x, yaw "
          f"rate), got {self.control_scale}, {self.residual_decay_s}"
      )

  @property
  def input_dim(self) -> int:
    """Width of the MLP input: ego features, log(1 + delta), token embedding."""
    return ego_motion.NUM_FEATURES + 1 + self.token_dim
