"""The two forms of predictive distribution that every scorer takes.

Positions are in metres in the scenario frame; T future steps (125 at 25 Hz).

- `WeightedSamples`: a discrete distribution, N trajectories per scenario with weights
  summing to 1 (cVMDx's N samples, uniform; the WTA MLP's heads with their p; a physics
  baseline as one point mass, N = 1; cVMDx's K hypotheses with their probabilities).
- `GaussianMixture`: K modes per scenario, each an axis-aligned Gaussian per step
  (independent across steps and axes), with mode weights; it has an exact per-step
  marginal density and is sampled into `WeightedSamples` for the sample-based scores.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class WeightedSamples:
  """points (M, N, T, 2) m; weights (M, N), each row summing to 1."""

  points: jax.Array
  weights: jax.Array

  @classmethod
  def uniform(cls, points) -> "WeightedSamples":
    """Equal weights 1 / N for points (M, N, T, 2)."""
    m, n = points.shape[:2]
    return cls(points=points, weights=jnp.full((m, n), 1.0 / n, points.dtype))

  @classmethod
  def point_mass(cls, trajectory) -> "WeightedSamples":
    """One trajectory (M, T, 2) with weight 1."""
    return cls(
        points=trajectory[:, None],
        weights=jnp.ones(trajectory.shape[:1], trajectory.dtype)[:, None],
    )

  def mean(self):
    """Weighted mean trajectory (M, T, 2)."""
    return jnp.einsum("mn,mntd->mtd", self.weights, self.points)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class GaussianMixture:
  """means (M, K, T, 2) m, stds (M, K, T, 2) m (> 0), weights (M, K) summing to 1."""

  means: jax.Array
  stds: jax.Array
  weights: jax.Array

  def log_density(self, positions):
    """Exact log density (nats, per m^2) of positions (M, T, 2) under each step's
    marginal mixture -> (M, T)."""
    z = (positions[:, None] - self.means) / self.stds  # (M, K, T, 2)
    log_pdf = jnp.sum(
        -0.5 * z**2 - jnp.log(self.stds) - 0.5 * math.log(2.0 * math.pi), axis=-1
    )  # (M, K, T)
    log_w = jnp.log(jnp.maximum(self.weights, 1e-30))[..., None]
    return jax.scipy.special.logsumexp(log_pdf + log_w, axis=1)

  def sample(self, key: jax.Array, n: int) -> WeightedSamples:
    """n trajectories per scenario (mode by weight, then independent per-step noise),
    uniform weights."""
    mode_key, noise_key = jax.random.split(key)
    m = self.weights.shape[0]
    modes = jax.random.categorical(
        mode_key, jnp.log(jnp.maximum(self.weights, 1e-30)), shape=(n, m)
    ).T  # (M, n)
    pick = lambda a: jnp.take_along_axis(a, modes[:, :, None, None], axis=1)
    noise = jax.random.normal(noise_key, (m, n) + self.means.shape[2:], self.means.dtype)
    return WeightedSamples.uniform(pick(self.means) + pick(self.stds) * noise)

  def mean(self):
    """Mixture mean trajectory (M, T, 2)."""
    return jnp.einsum("mk,mktd->mtd", self.weights, self.means)
