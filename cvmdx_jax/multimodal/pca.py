"""Batched PCA of small point sets (one set per scenario).

Each scenario's N flattened trajectories are centred on their mean and
projected onto their top-r principal axes. With N = 9 samples of D = 250
coordinates, the scores come from the small N x N Gram matrix G = X X^T of
the centred X = U S V^T: G = U S^2 U^T, so scores = X V = U S (an eigh of
9 x 9 matrices is ~10x faster than an SVD of 9 x 250 ones on CPU). The sign
of each axis is arbitrary; everything downstream (GMM likelihood, BIC,
farthest-point seeding) is invariant to it.
"""

import jax
import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.errors import UserError


def project(points: jax.Array, dim: int) -> jax.Array:
  """Principal-component scores of each set of points.

  Args:
    points: (..., N, D) points, one set of N per leading index.
    dim: number r of components kept, 1 <= r <= min(N, D).

  Returns:
    (..., N, r) scores, centred per set (column means zero), ordered by
    decreasing explained variance.

  Raises:
    ValueError: `dim` out of range for the given shape.
  """
  num_points, num_features = points.shape[-2:]
  if not 1 <= dim <= min(num_points, num_features):
    raise UserError(
        f"pca_dim must be in [1, min(N, D)] = [1, {min(num_points, num_features)}] "
        f"for points of shape {points.shape}, got {dim}"
    )
  centred = points - jnp.mean(points, axis=-2, keepdims=True)
  gram = jnp.matmul(
      centred, jnp.swapaxes(centred, -1, -2), precision=constants.EXACT_MATMUL
  )  # (..., N, N)
  eigvals, eigvecs = jnp.linalg.eigh(gram)  # ascending
  top_vals = eigvals[..., ::-1][..., :dim]
  top_vecs = eigvecs[..., ::-1][..., :dim]
  return top_vecs * jnp.sqrt(jnp.maximum(top_vals, 0.0))[..., None, :]
