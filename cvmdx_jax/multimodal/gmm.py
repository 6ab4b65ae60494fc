"""Full-covariance Gaussian mixture fitted by EM, for one small point set.

Written for one set of N points in r dimensions and a component count C that
may be traced (so `jax.vmap` can run C = 1..C_max and many scenarios at once):
every mixture has `max_components` slots, of which the first C are active;
inactive slots have weight 0 and never receive responsibility.

Initialisation is deterministic (no random restarts): farthest-point seeding
(the first seed is the point farthest from the centroid, each next one the
point farthest from all seeds so far; ties go to the lowest index), every
point is assigned to its nearest active seed, and one M-step on that hard
assignment gives the starting mixture. EM then runs a fixed number of
iterations (E-step, M-step), as scikit-learn's GaussianMixture does with
tol = 0 and max_iter = num_iters when given the same starting parameters.

Covariances are regularised by adding `reg_covar` to the diagonal in every
M-step; component counts get 10 eps, as in scikit-learn, so empty components
stay finite (mean 0, covariance reg_covar * I).

References:
  BIC = -2 ln L + p ln N, p = C (r + r (r + 1) / 2 + 1) - 1 (Schwarz 1978;
  6C - 1 for r = 2, as in the cVMDx paper).
"""

import dataclasses
import math

import jax
import jax.numpy as jnp

from cvmdx_jax import constants


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Mixture:
  """Parameters of a Gaussian mixture with K slots in r dimensions.

  Attributes:
    weights: (K,) mixing weights, 0 for inactive slots, summing to 1.
    means: (K, r) component means.
    covariances: (K, r, r) component covariances (regularised).
  """

  weights: jax.Array
  means: jax.Array
  covariances: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Fit:
  """Result of `fit`.

  Attributes:
    mixture: the fitted `Mixture`.
    log_likelihood: () total log-likelihood of the points under `mixture`;
      -inf where it is not finite (so BIC never selects a broken fit).
    responsibilities: (N, K) posterior component probabilities under
      `mixture`, 0 in inactive slots.
  """

  mixture: Mixture
  log_likelihood: jax.Array
  responsibilities: jax.Array


def farthest_point_seeds(points: jax.Array, num_seeds: int) -> jax.Array:
  """Indices of `num_seeds` points chosen by greedy farthest-point traversal.

  Args:
    points: (N, r) points.
    num_seeds: static number of seeds, <= N.

  Returns:
    (num_seeds,) int indices; the first k of them are the seeds for k
    components, whatever num_seeds is.
  """

  def sq_dist_to(point):
    return jnp.sum((points - point) ** 2, axis=-1)

  first = jnp.argmax(sq_dist_to(jnp.mean(points, axis=0)))

  def next_seed(carry, _):
    min_dist, last = carry
    min_dist = jnp.minimum(min_dist, sq_dist_to(points[last]))
    seed = jnp.argmax(min_dist)
    return (min_dist, seed), seed

  init = (jnp.full(points.shape[:1], jnp.inf, points.dtype), first)
  _, rest = jax.lax.scan(next_seed, init, None, length=num_seeds - 1)
  return jnp.concatenate([first[None], rest])


def initial_responsibilities(
    points: jax.Array, num_components: jax.Array, max_components: int
) -> jax.Array:
  """Hard assignment of each point to its nearest active farthest-point seed.

  Args:
    points: (N, r) points.
    num_components: () int C in [1, max_components] (may be traced).
    max_components: static number K of slots.

  Returns:
    (N, K) one-hot responsibilities, 0 in slots >= C.
  """
  seeds = points[farthest_point_seeds(points, max_components)]
  sq_dist = jnp.sum((points[:, None, :] - seeds[None]) ** 2, axis=-1)
  active = jnp.arange(max_components) < num_components
  sq_dist = jnp.where(active, sq_dist, jnp.inf)
  return jax.nn.one_hot(jnp.argmin(sq_dist, axis=-1), max_components, dtype=points.dtype)


def m_step(
    points: jax.Array, responsibilities: jax.Array, active: jax.Array, reg_covar: float
) -> Mixture:
  """Maximum-likelihood mixture for given responsibilities.

  Args:
    points: (N, r) points.
    responsibilities: (N, K) soft assignments, 0 in inactive slots.
    active: (K,) bool, which slots are in use.
    reg_covar: value added to every covariance diagonal.

  Returns:
    The `Mixture`.
  """
  dim = points.shape[-1]
  counts = jnp.sum(responsibilities, axis=0) + 10 * jnp.finfo(points.dtype).eps
  means = jnp.matmul(responsibilities.T, points, precision=constants.EXACT_MATMUL) / counts[:, None]
  diff = points[None] - means[:, None]  # (K, N, r)
  scatter = jnp.einsum(
      "nk,kni,knj->kij", responsibilities, diff, diff, precision=constants.EXACT_MATMUL
  )
  covariances = scatter / counts[:, None, None] + reg_covar * jnp.eye(dim, dtype=points.dtype)
  weights = jnp.where(active, counts, 0.0)
  return Mixture(weights / jnp.sum(weights), means, covariances)


def _cholesky_whiten(covariances: jax.Array, diff: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Squared Mahalanobis norms and log-determinants through a Cholesky factor.

  Unrolled over the small static dimension r, so XLA fuses it into
  elementwise work instead of one LAPACK call per r x r matrix (~10x faster
  on CPU for r = 2). A matrix that is not positive definite gives NaN.

  Args:
    covariances: (K, r, r) symmetric positive definite matrices.
    diff: (K, N, r) vectors to whiten by the matching matrix.

  Returns:
    (K, N) squared norms diff^T cov^-1 diff and (K,) log det(cov).
  """
  dim = covariances.shape[-1]
  chol = [[None] * dim for _ in range(dim)]  # chol[i][j]: (K,) entry i, j
  for j in range(dim):
    chol[j][j] = jnp.sqrt(covariances[:, j, j] - sum(chol[j][k] ** 2 for k in range(j)))
    for i in range(j + 1, dim):
      dot = sum(chol[i][k] * chol[j][k] for k in range(j))
      chol[i][j] = (covariances[:, i, j] - dot) / chol[j][j]
  white = []  # forward substitution chol @ white = diff, one (K, N) row at a time
  for i in range(dim):
    dot = sum(chol[i][k][:, None] * white[k] for k in range(i))
    white.append((diff[..., i] - dot) / chol[i][i][:, None])
  log_det = 2 * sum(jnp.log(chol[i][i]) for i in range(dim))
  return sum(w**2 for w in white), log_det


def component_log_densities(points: jax.Array, mixture: Mixture) -> jax.Array:
  """log(weight_k) + log N(z_n | mean_k, cov_k) for every point and slot.

  Args:
    points: (N, r) points.
    mixture: `Mixture` with K slots.

  Returns:
    (N, K) weighted log densities; -inf in slots of weight 0.
  """
  dim = points.shape[-1]
  diff = points[None] - mixture.means[:, None]  # (K, N, r)
  mahalanobis, log_det = _cholesky_whiten(mixture.covariances, diff)
  log_norm = -0.5 * (dim * math.log(2 * math.pi) + log_det)
  log_weights = jnp.where(mixture.weights > 0, jnp.log(mixture.weights), -jnp.inf)
  return (log_weights[:, None] + log_norm[:, None] - 0.5 * mahalanobis).T


def _posterior(points: jax.Array, mixture: Mixture) -> tuple[jax.Array, jax.Array]:
  """(N, K) responsibilities and (N,) per-point log-likelihoods."""
  log_dens = component_log_densities(points, mixture)
  log_like = jax.nn.logsumexp(log_dens, axis=-1)
  return jnp.exp(log_dens - log_like[:, None]), log_like


def fit(
    points: jax.Array,
    num_components: jax.Array,
    max_components: int,
    reg_covar: float,
    num_iters: int,
) -> Fit:
  """Fits a C-component full-covariance mixture by deterministic EM.

  Args:
    points: (N, r) points.
    num_components: () int C in [1, max_components] (may be traced).
    max_components: static number K of slots.
    reg_covar: covariance floor added to the diagonal, in units of `points`^2.
    num_iters: static number of EM iterations after initialisation.

  Returns:
    `Fit` with the mixture, its total log-likelihood and responsibilities.
  """
  active = jnp.arange(max_components) < num_components
  init = m_step(
      points, initial_responsibilities(points, num_components, max_components), active, reg_covar
  )

  def em_iteration(_, mixture):
    responsibilities, _ = _posterior(points, mixture)
    return m_step(points, responsibilities, active, reg_covar)

  mixture = jax.lax.fori_loop(0, num_iters, em_iteration, init)
  responsibilities, log_like = _posterior(points, mixture)
  total = jnp.sum(log_like)
  total = jnp.where(jnp.isfinite(total), total, -jnp.inf)
  return Fit(mixture, total, responsibilities)


def num_parameters(num_components, dim: int):
  """Free parameters of a C-component full-covariance mixture in `dim` dims."""
  return num_components * (dim + dim * (dim + 1) // 2 + 1) - 1


def bic(log_likelihood, num_components, dim: int, num_points: int):
  """Bayesian information criterion -2 ln L + p ln N (lower is better)."""
  return -2 * log_likelihood + num_parameters(num_components, dim) * math.log(num_points)
