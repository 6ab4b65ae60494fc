"""Densities of the position at 1..5 s, their NLL, and highest-density prediction regions.

Every model's prediction at a horizon becomes a 2-D mixture of axis-aligned Gaussians
(`HorizonMixture`, per scenario K components):
- a `GaussianMixture` (the MDN): its own components at that step (exact density);
- `WeightedSamples` (cVMDx's samples, its hypotheses, the WTA heads, a point mass): a
  Gaussian kernel on each point with its weight and, per scenario m and axis a (lon, lat),
  the bandwidth h_{m,a} = sqrt((c sd_{m,a})^2 + f_a^2), sd_{m,a} the weighted standard
  deviation of the scenario's points at that horizon (`spread`): a kernel that grows with
  the model's own spread (c, Silverman-like) above a floor f. The rule (c, f_lon, f_lat)
  is chosen per model and horizon on val by the smallest mean NLL over `SCALE_GRID` x
  `BANDWIDTH_GRID_M`^2 (`choose_bandwidth`); c = 0 is one fixed bandwidth for every
  scenario (the density used before 2026-12-06 evening). For a point mass (sd = 0) this is
  a Gaussian around it whose spread is fitted on val.
- `WeightedSamples` with a cluster per point (cVMDx's samples and their hypothesis labels):
  a Gaussian per cluster, weighted by the cluster's share of the samples, at the cluster's
  mean with per-axis width sqrt((c sd_{m,k,a})^2 + f_a^2), sd the cluster's own (maximum
  likelihood) spread; the rule chosen on val in the same way (`components`).
- either may carry a wide tail (`with_tail`): a further component of weight eps at the
  scenario's weighted mean with widths lam * sqrt((c sd_all)^2 + f^2), sd_all the spread of
  all its points, so that a truth outside every kernel or cluster costs -log eps plus a
  wide Gaussian's NLL instead of a squared distance over a narrow width. The rule is then
  (c, f_lon, f_lat, eps, lam), eps from `TAIL_WEIGHTS` and lam from `TAIL_WIDTHS` chosen with
  (c, f) on val; eps = 0 (or a rule of three) is the density without it.

`nll` is -log p(y) in nats (density per m^2). The highest-density region (HDR) of level
a is {z : p(z) >= t_a} with mass a; `hdr` draws `HDR_DRAWS` positions z from p and
returns per scenario u = P(p(Z) > p(y)), the mass of the smallest HDR that holds the
truth (y lies in the level-a region iff u <= a, so the share of u <= a is the coverage
and the curve over a the reliability curve), and the area (m^2) of the level-a regions,
E[1{p(Z) >= t_a} / p(Z)] over the draws.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.evaluation import probabilistic
from cvmdx_jax.inference.distributions import GaussianMixture, WeightedSamples

HORIZONS_S = (1, 2, 3, 4, 5)
HORIZON_STEPS = tuple(round(s / constants.DT) - 1 for s in HORIZONS_S)  # future index at s
LEVELS = (0.5, 0.9, 0.95)  # nominal masses of the reported regions
BANDWIDTH_GRID_M = tuple(float(h) for h in np.geomspace(0.01, 30.0, 36))  # floors f
SCALE_GRID = (0.0,) + tuple(float(c) for c in np.geomspace(0.1, 3.0, 15))  # factors c
TAIL_WEIGHTS = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1)  # eps of the wide tail
TAIL_WIDTHS = (3.0, 10.0, 30.0)  # lam: the tail's widths over the scenario's kernel width
HDR_DRAWS = 256  # Monte Carlo draws per scenario and horizon for u and the areas
_CHUNK = 256  # scenarios per vectorised block (bounds memory at M x N x G x G)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class HorizonMixture:
  """means, stds (M, K, 2) m (axis-aligned), weights (M, K): the density at one horizon."""

  means: jax.Array
  stds: jax.Array
  weights: jax.Array


def moments(points, weights):
  """Weighted mean and standard deviation per axis of each scenario's points: (M, N, 2),
  (M, N) -> (M, 2), (M, 2) m (sd 0 for a point mass)."""
  w = weights / jnp.sum(weights, axis=1, keepdims=True)
  mean = jnp.einsum("mn,mna->ma", w, points)
  return mean, jnp.sqrt(jnp.einsum("mn,mna->ma", w, (points - mean[:, None]) ** 2))


def kernel_widths(sd, rule):
  """Kernel bandwidths sqrt((c sd)^2 + f^2) (m) of rule (c, f_lon, f_lat, ...); sd (..., 2)."""
  c, floor = rule[0], jnp.asarray(rule[1:3], sd.dtype)
  return jnp.sqrt((c * sd) ** 2 + floor**2)


def with_tail(mix: HorizonMixture, centre, sd_all, rule) -> HorizonMixture:
  """`mix` with the wide tail of rule (c, f_lon, f_lat, eps, lam) (module docstring):
  centre, sd_all (M, 2) m the mean and spread of all the scenario's points."""
  eps, lam = rule[3], rule[4]
  return HorizonMixture(
      jnp.concatenate([mix.means, centre[:, None]], axis=1),
      jnp.concatenate([mix.stds, lam * kernel_widths(sd_all, rule)[:, None]], axis=1),
      jnp.concatenate([(1.0 - eps) * mix.weights, jnp.full_like(mix.weights[:, :1], eps)], axis=1),
  )


def _at_step(dist: WeightedSamples, step: int):
  """The points (M, N, 2) at future index `step` and their weights (M, N), float32."""
  return jnp.asarray(dist.points, jnp.float32)[:, :, step], jnp.asarray(dist.weights, jnp.float32)


def components(dist: WeightedSamples, step: int, labels=None):
  """Centres (M, K, 2), weights (M, K) and spreads sd (M, K, 2) of the density's components
  at `step`: every point with the scenario's spread, or (labels (M, N) int, the cluster of
  each point) every cluster's mean, share and own spread (module docstring)."""
  points, weights = _at_step(dist, step)
  if labels is None:
    return points, weights, jnp.broadcast_to(moments(points, weights)[1][:, None], points.shape)
  clusters = int(np.max(labels)) + 1
  means, cov = probabilistic.hypothesis_covariances(points, jnp.asarray(labels), clusters, 0.0)
  share = jnp.mean(jax.nn.one_hot(jnp.asarray(labels), clusters, dtype=jnp.float32), axis=1)
  sd = jnp.sqrt(jnp.maximum(jnp.diagonal(cov, axis1=-2, axis2=-1), 0.0))
  return means, share, sd


def at_horizon(dist, step: int, bandwidth=None, labels=None) -> HorizonMixture:
  """The density of `dist` at future index `step`; bandwidth: the rule (c, f_lon, f_lat[,
  eps, lam]) (module docstring) for `WeightedSamples` (labels: a cluster per point, see
  `components`), None for a `GaussianMixture`."""
  if isinstance(dist, GaussianMixture):
    return HorizonMixture(dist.means[:, :, step], dist.stds[:, :, step], dist.weights)
  rule = tuple(float(v) for v in bandwidth)
  centres, weights, sd = components(dist, step, labels)
  mix = HorizonMixture(centres, kernel_widths(sd, rule), weights)
  if len(rule) < 5 or rule[3] == 0.0:
    return mix
  return with_tail(mix, *moments(*_at_step(dist, step)), rule)


def _component_log_pdf(mix: HorizonMixture, z):
  """log w_k + log N(z | mu_k, diag s_k^2): z (M, D, 2) -> (M, D, K)."""
  d = (z[:, :, None] - mix.means[:, None]) / mix.stds[:, None]
  log_norm = jnp.sum(jnp.log(mix.stds), axis=-1) + math.log(2.0 * math.pi)  # (M, K)
  log_w = jnp.log(jnp.maximum(mix.weights, 1e-30))
  return log_w[:, None] - log_norm[:, None] - 0.5 * jnp.sum(d * d, axis=-1)


@jax.jit
def log_density(mix: HorizonMixture, z):
  """log p(z) (nats per m^2) of z (M, D, 2) under each scenario's mixture -> (M, D)."""
  return jax.scipy.special.logsumexp(_component_log_pdf(mix, z), axis=-1)


def nll(mix: HorizonMixture, y):
  """-log p(y) in nats of the true positions y (M, 2) -> (M,)."""
  return -log_density(mix, jnp.asarray(y)[:, None])[:, 0]


def _axis_log_pdf(dev, widths):
  """log N(dev | 0, widths^2) per axis; dev broadcast against widths."""
  return -0.5 * (dev / widths) ** 2 - jnp.log(widths) - 0.5 * math.log(2.0 * math.pi)


@jax.jit
def _grid_nll(points, weights, sd, centre, sd_all, y, valid, scale, grid, tails):
  """Sum over the valid scenarios of -log p(y) with component widths sqrt((scale sd)^2 +
  f^2), sd (M, N, 2), for every floor pair (f_lon, f_lat) of grid (G,) and tail (eps, lam)
  of tails ((E,), (L,)) -> (G, G, E, L); centre, sd_all (M, 2) as `with_tail`."""
  eps, lam = tails
  per_axis = _axis_log_pdf(
      (y[:, None] - points)[..., None], jnp.sqrt((scale * sd)[..., None] ** 2 + grid**2)
  )
  joint = per_axis[:, :, 0, :, None] + per_axis[:, :, 1, None, :]  # (M, N, G, G)
  log_w = jnp.log(jnp.maximum(weights, 1e-30))[..., None, None]
  main = jax.scipy.special.logsumexp(joint + log_w, axis=1)  # (M, G, G)
  base = jnp.sqrt((scale * sd_all)[..., None] ** 2 + grid**2)  # (M, 2, G)
  tail_axis = _axis_log_pdf((y - centre)[..., None, None], base[..., None] * lam)  # (M, 2, G, L)
  tail = tail_axis[:, 0, :, None, :] + tail_axis[:, 1, None, :, :]  # (M, G, G, L)
  per = jnp.logaddexp(
      jnp.log1p(-eps)[:, None] + main[..., None, None], jnp.log(eps)[:, None] + tail[:, :, :, None]
  )  # (M, G, G, E, L)
  return -jnp.sum(jnp.where(valid[:, None, None, None, None], per, 0.0), axis=0)


def choose_bandwidth(
    dist: WeightedSamples,
    gt,
    step: int,
    grid=BANDWIDTH_GRID_M,
    scales=SCALE_GRID,
    labels=None,
    tails=(TAIL_WEIGHTS, TAIL_WIDTHS),
) -> tuple[float, float, float, float, float]:
  """The rule (c, f_lon, f_lat, eps, lam) of `scales` x `grid`^2 x tails (eps values, lam
  values) with the smallest mean NLL of gt[:, step] (call it on val; ties go to the smaller
  c, f and eps); labels as `components`."""
  points, weights, sd = (np.asarray(a) for a in components(dist, step, labels))
  centre, sd_all = (np.asarray(a) for a in moments(*_at_step(dist, step)))
  y = np.asarray(gt, np.float32)[:, step]
  grid = jnp.asarray(grid, jnp.float32)
  tails_arr = tuple(jnp.asarray(t, jnp.float32) for t in tails)
  size = min(_CHUNK, len(y))
  blocks = [
      tuple(_pad(a[i:j], size) for a in (points, weights, sd, centre, sd_all, y))
      + (jnp.arange(size) < j - i,)
      for i, j in _blocks(len(y))
  ]
  totals = np.stack(
      [
          np.asarray(sum(_grid_nll(*block, jnp.float32(c), grid, tails_arr) for block in blocks))
          for c in scales
      ]
  )  # (C, G, G, E, L)
  c, lon, lat, e, w = np.unravel_index(int(np.argmin(totals)), totals.shape)
  values = (scales[c], grid[lon], grid[lat], tails[0][e], tails[1][w])
  return tuple(round(float(v), 4) for v in values)


def _draw(key, mix: HorizonMixture, n: int):
  """n positions per scenario from the mixture -> (M, n, 2)."""
  k_key, z_key = jax.random.split(key)
  comp = jax.random.categorical(
      k_key, jnp.log(jnp.maximum(mix.weights, 1e-30))[:, None], shape=(mix.weights.shape[0], n)
  )
  pick = lambda a: jnp.take_along_axis(a, comp[..., None], axis=1)
  return pick(mix.means) + pick(mix.stds) * jax.random.normal(z_key, comp.shape + (2,))


@jax.jit
def _hdr_block(key, mix: HorizonMixture, y, levels):
  draws = _draw(key, mix, HDR_DRAWS)
  logp = log_density(mix, draws)  # (M, D)
  logp_y = log_density(mix, y[:, None])  # (M, 1)
  u = jnp.mean(logp > logp_y, axis=-1)
  inv = jnp.sort(-logp, axis=-1)  # descending density: -log p ascending
  cum_area = jnp.cumsum(jnp.exp(inv), axis=-1) / HDR_DRAWS  # (M, D)
  index = jnp.clip(jnp.ceil(levels * HDR_DRAWS).astype(jnp.int32) - 1, 0, HDR_DRAWS - 1)
  return u, jnp.take_along_axis(cum_area, index, axis=-1)


def _blocks(m: int):
  """(start, stop) of the `_CHUNK` blocks of m scenarios; the last one is padded by `_pad`
  (one compiled shape per call site)."""
  return [(i, min(i + _CHUNK, m)) for i in range(0, m, _CHUNK)]


def _pad(a, size: int):
  """a (n, ...) padded to (size, ...) by repeating its first row."""
  a = jnp.asarray(a)
  return (
      a
      if a.shape[0] == size
      else jnp.concatenate([a, jnp.broadcast_to(a[:1], (size - a.shape[0],) + a.shape[1:])])
  )


def hdr(key: jax.Array, mix: HorizonMixture, y, levels) -> tuple[np.ndarray, np.ndarray]:
  """Per scenario u = P(p(Z) > p(y)) (M,) and the areas (m^2) of the level-`levels` HDRs.

  levels: (L,) shared or (M, L) per scenario (calibrated levels). Returns u (M,), area (M, L).
  """
  y = jnp.asarray(y)
  m = y.shape[0]
  levels = np.broadcast_to(np.asarray(levels, np.float32), (m, np.shape(levels)[-1]))
  size = min(_CHUNK, m)
  us, areas = [], []
  for i, j in _blocks(m):
    part = jax.tree.map(lambda a: _pad(a[i:j], size), mix)
    u, area = _hdr_block(
        jax.random.fold_in(key, i), part, _pad(y[i:j], size), _pad(levels[i:j], size)
    )
    us.append(np.asarray(u)[: j - i])
    areas.append(np.asarray(area)[: j - i])
  return np.concatenate(us), np.concatenate(areas)
