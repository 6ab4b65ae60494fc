"""Vector quantisation of scenario latents: plain VQ and CVQ behind one interface.

Both quantise z_hat to its nearest codebook entry with the straight-through estimator
and the VQ-VAE losses (van den Oord et al. 2017): codebook ||sg[z_hat] - z_q||^2 and
commitment beta ||z_hat - sg[z_q]||^2. The codebook is an ordinary parameter (the
codebook loss trains it).

CVQ (Zheng & Vedaldi, "Online Clustered Codebook", ICCV 2023) adds, after each
optimiser step, a refresh of rarely used entries. It keeps a running average of each
entry's share of the batch,
    N_k <- gamma N_k + (1 - gamma) n_k / B,
and moves every entry toward an anchor drawn from the batch's encoded features,
    z_k <- (1 - alpha_k) z_k + alpha_k anchor_k,
    alpha_k = exp(-N_k Q strength / (1 - gamma) - eps).
An entry used at the average rate has N_k ~ 1/Q and alpha_k ~ exp(-strength / (1 -
gamma)) ~ 0; an entry unused for a while has N_k -> 0 and alpha_k -> 1, so it jumps to
where the data is and no entry stays dead. Anchors are batch features drawn at random
(with probability proportional to the row weight, so padding rows are never drawn).
`usage` starts at 0, so the first step places every entry on a data point.
For VQ, `update_codebook` only tracks the running usage (for logging) and leaves the
codebook alone.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.config.models import QuantizerConfig

_EPS = 1e-3  # the eps of alpha_k: keeps alpha_k < 1


class Quantized(NamedTuple):
  """Output of `quantize` for B latents.

  Attributes:
    z_q: (B, D) straight-through quantised latents (value z_q, gradient to z_hat).
    indices: (B,) int32 token q of each latent.
    codebook_loss: (B,) ||sg[z_hat] - z_q||^2, mean over D.
    commitment_loss: (B,) ||z_hat - sg[z_q]||^2, mean over D (beta not applied).
  """

  z_q: jax.Array
  indices: jax.Array
  codebook_loss: jax.Array
  commitment_loss: jax.Array


def init_codebook(key: jax.Array, config: QuantizerConfig) -> jax.Array:
  """(Q, D) entries uniform in [-1/Q, 1/Q] (the usual VQ-VAE initialisation)."""
  q = config.codebook_size
  return jax.random.uniform(key, (q, config.latent_dim), jnp.float32, -1.0 / q, 1.0 / q)


def nearest(codebook: jax.Array, z_hat: jax.Array) -> jax.Array:
  """(Q, D) codebook, (B, D) latents -> (B,) int32 index of the nearest entry (L2)."""
  d2 = (
      jnp.sum(z_hat**2, -1, keepdims=True)
      - 2.0 * jnp.matmul(z_hat, codebook.T, precision=constants.EXACT_MATMUL)
      + jnp.sum(codebook**2, -1)
  )
  return jnp.argmin(d2, axis=-1).astype(jnp.int32)


def quantize(codebook: jax.Array, z_hat: jax.Array) -> Quantized:
  """Nearest-entry quantisation with straight-through gradients.

  Args:
    codebook: (Q, D).
    z_hat: (B, D) encoder outputs.
  """
  indices = nearest(codebook, z_hat)
  z_q = codebook[indices]
  codebook_loss = jnp.mean((jax.lax.stop_gradient(z_hat) - z_q) ** 2, -1)
  commitment_loss = jnp.mean((z_hat - jax.lax.stop_gradient(z_q)) ** 2, -1)
  z_st = z_hat + jax.lax.stop_gradient(z_q - z_hat)
  return Quantized(z_st, indices, codebook_loss, commitment_loss)


def init_usage(config: QuantizerConfig) -> jax.Array:
  """(Q,) running usage, all zero."""
  return jnp.zeros((config.codebook_size,), jnp.float32)


def batch_share(indices: jax.Array, weight: jax.Array, num_entries: int) -> jax.Array:
  """(B,) indices, (B,) row weights -> (Q,) weighted share of the batch per entry."""
  counts = jax.ops.segment_sum(weight, indices, num_segments=num_entries)
  return counts / jnp.maximum(jnp.sum(weight), 1e-12)


def update_codebook(
    codebook: jax.Array,
    usage: jax.Array,
    z_hat: jax.Array,
    indices: jax.Array,
    weight: jax.Array,
    key: jax.Array,
    config: QuantizerConfig,
) -> tuple[jax.Array, jax.Array]:
  """Running usage update and, for CVQ, the anchor refresh of low-usage entries.

  Args:
    codebook: (Q, D) entries after the optimiser step.
    usage: (Q,) running usage N.
    z_hat: (B, D) encoder outputs of the batch (gradients are stopped here).
    indices: (B,) their tokens.
    weight: (B,) row weights (0 for padding rows).
    key: PRNG key for drawing the anchors.
    config: the quantiser settings.

  Returns:
    (codebook, usage), same shapes.
  """
  gamma = config.usage_decay
  usage = gamma * usage + (1.0 - gamma) * batch_share(indices, weight, config.codebook_size)
  if config.kind == "vq":
    return codebook, usage
  rows = jax.random.choice(
      key, weight.shape[0], (config.codebook_size,), p=weight / jnp.maximum(jnp.sum(weight), 1e-12)
  )
  anchors = jax.lax.stop_gradient(z_hat[rows])
  alpha = jnp.exp(-usage * config.codebook_size * config.revive_strength / (1.0 - gamma) - _EPS)[
      :, None
  ]
  return (1.0 - alpha) * codebook + alpha * anchors, usage


def codebook_stats(
    indices: jax.Array, num_entries: int, weight: jax.Array | None = None
) -> tuple[jax.Array, jax.Array]:
  """Entries in use and perplexity of an assignment.

  Args:
    indices: (M,) tokens.
    num_entries: Q.
    weight: (M,) row weights, default all ones.

  Returns:
    (entries with at least one (weighted) member, exp(entropy of the token shares)).
  """
  if weight is None:
    weight = jnp.ones(indices.shape, jnp.float32)
  share = batch_share(indices, weight, num_entries)
  in_use = jnp.sum(share > 0)
  entropy = -jnp.sum(jnp.where(share > 0, share * jnp.log(jnp.where(share > 0, share, 1.0)), 0.0))
  return in_use, jnp.exp(entropy)
