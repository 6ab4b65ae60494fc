"""The scenario tokeniser: encoder E, (C)VQ codebook, decoder D, maneuver classifier.

Loss (paper, "Context Conditioning via CVQ-VAE"):
    L = ||xi - D(z_q)||^2 + ||sg[E(xi)] - z_q||^2 + beta ||E(xi) - sg[z_q]||^2
        + lambda CE(softmax(f_cl(z_q)), s),
with the reconstruction error over the normalised features of present vehicles only
(mean over the mask), f_cl a linear layer on the straight-through z_q, and every term
a weighted mean over the batch rows (padding rows have weight 0).

Functional use, as the U-Net's: `graphdef, params = init_tokenizer(config, key)`, then
`apply_tokenizer` / `encode` / `classify` with (graphdef, params) inside `jax.jit`.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import nnx

from cvmdx_jax import constants
from cvmdx_jax.config.models import TokenizerConfig
from cvmdx_jax.models import functional, scenario_norm
from cvmdx_jax.models import quantizer as quantizer_lib
from cvmdx_jax.models.scenario_encoder import ScenarioDecoder, ScenarioEncoder


class Output(NamedTuple):
  """Forward pass on B scenarios.

  Attributes:
    z_hat: (B, D) encoder latents.
    quantized: the quantiser output (straight-through z_q, tokens, VQ losses).
    reconstruction: (B, 9, 75, 4) normalised xi reconstructed from z_q.
    logits: (B, 3) maneuver logits from z_q.
  """

  z_hat: jax.Array
  quantized: quantizer_lib.Quantized
  reconstruction: jax.Array
  logits: jax.Array


class Tokenizer(nnx.Module):
  """E + codebook + D + linear maneuver classifier."""

  def __init__(self, config: TokenizerConfig, *, rngs: nnx.Rngs):
    self.encoder = ScenarioEncoder(config.encoder, rngs=rngs)
    self.decoder = ScenarioDecoder(config.encoder, rngs=rngs)
    self.codebook = nnx.Param(quantizer_lib.init_codebook(rngs.params(), config.quantizer))
    self.classifier = nnx.Linear(config.encoder.latent_dim, constants.NUM_CLASSES, rngs=rngs)

  def encode(self, xi: jax.Array, mask: jax.Array) -> jax.Array:
    """(B, 9, 75, 4) physical xi, (B, 9, 75) mask -> (B, D) z_hat."""
    return self.encoder(scenario_norm.encoder_input(xi, mask))

  def __call__(self, xi: jax.Array, mask: jax.Array) -> Output:
    z_hat = self.encode(xi, mask)
    quantized = quantizer_lib.quantize(self.codebook[...], z_hat)
    return Output(z_hat, quantized, self.decoder(quantized.z_q), self.classifier(quantized.z_q))


def init_tokenizer(config: TokenizerConfig, key: jax.Array):
  """Builds the model; returns (graphdef, params), params a pure dict of arrays."""
  return functional.init(lambda rngs: Tokenizer(config, rngs=rngs), key)


def make_graphdef(config: TokenizerConfig):
  """The graph definition alone (no parameters are allocated)."""
  return functional.make_graphdef(Tokenizer, config)


def abstract_params(config: TokenizerConfig) -> dict:
  """The parameters' shapes and dtypes (`jax.ShapeDtypeStruct`s; nothing is allocated)."""
  return functional.abstract_params(Tokenizer, config)


def apply_tokenizer(graphdef, params, xi: jax.Array, mask: jax.Array) -> Output:
  """Functional forward pass on (B, 9, 75, 4) physical xi and (B, 9, 75) mask."""
  return nnx.merge(graphdef, params)(xi, mask)


def encode(graphdef, params, xi: jax.Array, mask: jax.Array) -> tuple[jax.Array, jax.Array]:
  """(B, 9, 75, 4) physical xi, (B, 9, 75) mask -> (z_hat (B, D), token q (B,) int32)."""
  model = nnx.merge(graphdef, params)
  z_hat = model.encode(xi, mask)
  return z_hat, quantizer_lib.nearest(model.codebook[...], z_hat)


def classify(graphdef, params, q: jax.Array) -> jax.Array:
  """Maneuver logits (..., 3) of tokens q (...,) from their codebook entries."""
  model = nnx.merge(graphdef, params)
  return model.classifier(model.codebook[...][q])


def weighted_mean(values: jax.Array, weight: jax.Array) -> jax.Array:
  """(B,) per-row values, (B,) weights -> scalar weighted mean (0 for all-zero weights)."""
  return jnp.sum(values * weight) / jnp.maximum(jnp.sum(weight), 1e-12)


def loss_fn(graphdef, params, batch: dict, config: TokenizerConfig):
  """Tokeniser loss on a batch.

  Args:
    graphdef, params: the tokeniser (`init_tokenizer`).
    batch: "xi" (B, 9, 75, 4), "mask" (B, 9, 75), "label" (B,) int, "weight" (B,).
    config: static settings (beta, lambda).

  Returns:
    (loss scalar, (metrics dict of scalars, Output)).
  """
  out = apply_tokenizer(graphdef, params, batch["xi"], batch["mask"])
  weight = batch["weight"].astype(jnp.float32)
  vehicle_weight = jnp.ones(constants.NUM_VEHICLES).at[0].set(config.ego_weight)
  mask = batch["mask"].astype(jnp.float32)[..., None] * vehicle_weight[:, None, None]
  target = scenario_norm.normalize_xi(batch["xi"], batch["mask"])
  sq_err = jnp.sum(mask * (out.reconstruction - target) ** 2, axis=(1, 2, 3))
  recon = sq_err / jnp.maximum(jnp.sum(mask, axis=(1, 2, 3)) * constants.NUM_FEATURES, 1.0)
  ce = optax.softmax_cross_entropy_with_integer_labels(out.logits, batch["label"])
  correct = (jnp.argmax(out.logits, -1) == batch["label"]).astype(jnp.float32)
  metrics = {
      "reconstruction": weighted_mean(recon, weight),
      "codebook": weighted_mean(out.quantized.codebook_loss, weight),
      "commitment": weighted_mean(out.quantized.commitment_loss, weight),
      "classification": weighted_mean(ce, weight),
      "accuracy": weighted_mean(correct, weight),
  }
  loss = (
      metrics["reconstruction"]
      + metrics["codebook"]
      + config.quantizer.beta * metrics["commitment"]
      + config.cls_weight * metrics["classification"]
  )
  return loss, (metrics, out)
