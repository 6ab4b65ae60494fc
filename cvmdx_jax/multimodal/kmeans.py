"""k-means (Lloyd's algorithm) over one small set of sampled trajectories.

Built for coverage at a fixed number of hypotheses K: where the GMM/BIC stage picks
how many modes the samples hold, k-means always splits them into K groups, so that
the best of the K group means lies close to the true future more often (minFDE_K).

Distance: squared Euclidean over the trajectory in metres with per-step weights
w_t = (1 - endpoint_weight) / T + endpoint_weight [t = T - 1] (`step_weights`):
endpoint_weight 0 is the plain mean squared displacement over the T steps,
1 the squared final displacement alone. Clustering runs on the features
sqrt(w_t) x_t, in which this distance is the plain squared Euclidean one.

Deterministic, no key: farthest-point seeding (`gmm.farthest_point_seeds`: the sample
farthest from the centroid, then each next the one farthest from all seeds so far,
ties to the lowest index), then a fixed number of Lloyd steps (assign every point to
its nearest centre, ties to the lower cluster index; move each centre to the mean of
its points; a centre with no points stays where it is), then a final assignment to
the last centres. With fewer distinct points than K, the surplus seeds repeat a point
and their clusters stay empty.
"""

import jax
import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.multimodal import gmm


def step_weights(num_steps: int, endpoint_weight: float, dtype=jnp.float32) -> jax.Array:
  """(T,) per-step weights of the distance, summing to 1 (see the module docstring)."""
  uniform = jnp.full((num_steps,), (1.0 - endpoint_weight) / num_steps, dtype)
  return uniform.at[-1].add(endpoint_weight)


def features(trajectories: jax.Array, endpoint_weight: float) -> jax.Array:
  """(..., N, T, 2) metres -> (..., N, 2T) points whose squared Euclidean distance is
  the weighted squared displacement sum_t w_t |x_t - x'_t|^2, in m^2."""
  weights = step_weights(trajectories.shape[-2], endpoint_weight, trajectories.dtype)
  scaled = trajectories * jnp.sqrt(weights)[:, None]
  return scaled.reshape(scaled.shape[:-2] + (-1,))


def assign(points: jax.Array, centers: jax.Array) -> jax.Array:
  """Index of the nearest centre of each point (ties: lowest index): (N, D), (K, D) -> (N,)."""
  sq_dist = jnp.sum((points[:, None, :] - centers[None]) ** 2, axis=-1)
  return jnp.argmin(sq_dist, axis=-1)


def update(points: jax.Array, labels: jax.Array, centers: jax.Array) -> jax.Array:
  """Mean of each cluster's points; an empty cluster keeps its centre. -> (K, D)."""
  one_hot = jax.nn.one_hot(labels, centers.shape[0], dtype=points.dtype)  # (N, K)
  counts = jnp.sum(one_hot, axis=0)
  sums = jnp.matmul(one_hot.T, points, precision=constants.EXACT_MATMUL)
  return jnp.where(counts[:, None] > 0, sums / jnp.maximum(counts, 1.0)[:, None], centers)


def fit(points: jax.Array, num_clusters: int, num_iters: int) -> tuple[jax.Array, jax.Array]:
  """k-means of one point set.

  Args:
    points: (N, D) points.
    num_clusters: static K (may exceed N: the surplus clusters stay empty).
    num_iters: static number of Lloyd steps (no early stop; a converged
      clustering is a fixed point, so more steps change nothing).

  Returns:
    centers (K, D) after `num_iters` steps and labels (N,) int, the nearest of them.
  """
  init = points[gmm.farthest_point_seeds(points, num_clusters)]

  def lloyd(centers, _):
    return update(points, assign(points, centers), centers), None

  centers, _ = jax.lax.scan(lloyd, init, None, length=num_iters)
  return centers, assign(points, centers)
