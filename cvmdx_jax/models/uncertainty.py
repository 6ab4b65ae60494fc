"""Scenario context uncertainty: per-entry Gaussians and the Mahalanobis distance delta.

For each codebook entry q (paper, "Scenario Context Uncertainty Estimation"):
    mu_q = z_q,  S_q = mean over the training latents assigned to q of (z - z_q)(z - z_q)^T,
    delta = sqrt((z_hat - mu_q)^T Sigma_q^{-1} (z_hat - mu_q)).
S_q is singular when q has fewer members than latent dimensions (and undefined with
none), so it is shrunk toward a pooled covariance:
    Sigma_q = n_q / (n_q + k) S_q + k / (n_q + k) P,
    P = (pooled S over all latents about their own entries) + ridge mean(diag) I + 1e-6 I,
where k (`shrinkage`, in pseudo-members) sets how many members an entry needs before
its own covariance dominates. P is positive definite, so every Sigma_q is invertible;
an entry without members gets Sigma_q = P.
"""

import dataclasses

import jax
import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.errors import UserError


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Gaussians:
  """Per-entry Gaussians N(mean_q, cov_q).

  Attributes:
    mean: (Q, D) the codebook entries z_q.
    cov: (Q, D, D) regularised covariances Sigma_q.
    precision: (Q, D, D) their inverses.
    count: (Q,) number of training latents assigned to each entry.
  """

  mean: jax.Array
  cov: jax.Array
  precision: jax.Array
  count: jax.Array


def fit_gaussians(
    z_hat: jax.typing.ArrayLike,
    indices: jax.typing.ArrayLike,
    codebook: jax.typing.ArrayLike,
    shrinkage: float = 16.0,
    ridge: float = 1e-3,
) -> Gaussians:
  """Fits the per-entry Gaussians from the training latents.

  Args:
    z_hat: (M, D) training latents.
    indices: (M,) their tokens.
    codebook: (Q, D) entries (the Gaussian means).
    shrinkage: k > 0, pseudo-members of the pooled covariance in each entry.
    ridge: relative diagonal loading of the pooled covariance.

  Returns:
    `Gaussians` with invertible covariances.
  """
  if shrinkage <= 0 or ridge < 0:
    raise UserError(
        f"uncertainty: shrinkage ({shrinkage}) must be > 0 and ridge " f"({ridge}) >= 0"
    )
  z_hat = jnp.asarray(z_hat, jnp.float32)
  codebook = jnp.asarray(codebook, jnp.float32)
  num_entries, dim = codebook.shape
  diff = z_hat - codebook[indices]
  outer = diff[:, :, None] * diff[:, None, :]
  scatter = jax.ops.segment_sum(outer, indices, num_segments=num_entries)
  count = jax.ops.segment_sum(
      jnp.ones_like(indices, jnp.float32), indices, num_segments=num_entries
  )
  eye = jnp.eye(dim, dtype=jnp.float32)
  pooled = jnp.sum(scatter, 0) / jnp.maximum(jnp.sum(count), 1.0)
  pooled = pooled + (ridge * jnp.mean(jnp.diag(pooled)) + 1e-6) * eye
  own = scatter / jnp.maximum(count, 1.0)[:, None, None]
  w = (count / (count + shrinkage))[:, None, None]
  cov = w * own + (1.0 - w) * pooled
  chol = jnp.linalg.cholesky(cov)
  chol_inv = jax.scipy.linalg.solve_triangular(chol, jnp.broadcast_to(eye, cov.shape), lower=True)
  precision = jnp.matmul(jnp.swapaxes(chol_inv, -1, -2), chol_inv, precision=constants.EXACT_MATMUL)
  return Gaussians(codebook, cov, precision, count)


def mahalanobis(
    z_hat: jax.typing.ArrayLike, indices: jax.typing.ArrayLike, gaussians: Gaussians
) -> jax.Array:
  """delta: (B, D) latents, (B,) their tokens -> (B,) Mahalanobis distance to their entry."""
  diff = jnp.asarray(z_hat, jnp.float32) - gaussians.mean[indices]
  quad = jnp.einsum(
      "bi,bij,bj->b", diff, gaussians.precision[indices], diff, precision=constants.EXACT_MATMUL
  )
  return jnp.sqrt(jnp.maximum(quad, 0.0))
