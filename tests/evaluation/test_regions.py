"""Horizon densities, val-chosen bandwidths and HDR regions against closed forms."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.evaluation import regions
from cvmdx_jax.inference.distributions import GaussianMixture, WeightedSamples


def test_horizon_steps_are_whole_seconds():
  assert regions.HORIZON_STEPS == (24, 49, 74, 99, 124)  # step i ends at (i + 1) / 25 s


def test_kernel_nll_is_the_hand_worked_mixture():
  points = jnp.asarray([[[[0.0, 0.0]], [[2.0, 0.0]]]])  # M 1, N 2, T 1
  dist = WeightedSamples(points, jnp.asarray([[0.25, 0.75]]))
  mix = regions.at_horizon(dist, 0, bandwidth=(0.0, 1.0, 0.5))  # c = 0: fixed widths
  y = np.array([[1.0, 0.5]])
  pdf = lambda mx: math.exp(-0.5 * ((1 - mx) ** 2 + 1.0)) / (2 * math.pi * 0.5)
  want = -math.log(0.25 * pdf(0.0) + 0.75 * pdf(2.0))
  np.testing.assert_allclose(np.asarray(regions.nll(mix, y)), [want], rtol=1e-5)


def test_spread_scaled_kernel_is_the_hand_worked_mixture():
  points = jnp.asarray([[[[0.0, 1.0]], [[2.0, 1.0]]]])  # lon spread: mean 1.5, sd sqrt(0.75)
  dist = WeightedSamples(points, jnp.asarray([[0.25, 0.75]]))
  mix = regions.at_horizon(dist, 0, bandwidth=(2.0, 0.5, 0.3))
  h_lon, h_lat = math.sqrt(4.0 * 0.75 + 0.25), 0.3  # sqrt((c sd)^2 + f^2); lat sd = 0
  np.testing.assert_allclose(np.asarray(mix.stds)[0, :, 0], [h_lon, h_lon], rtol=1e-6)
  np.testing.assert_allclose(np.asarray(mix.stds)[0, :, 1], [h_lat, h_lat], rtol=1e-6)
  y = np.array([[1.0, 1.2]])
  pdf = lambda mx: math.exp(-0.5 * (((1 - mx) / h_lon) ** 2 + (0.2 / h_lat) ** 2)) / (
      2 * math.pi * h_lon * h_lat
  )
  want = -math.log(0.25 * pdf(0.0) + 0.75 * pdf(2.0))
  np.testing.assert_allclose(np.asarray(regions.nll(mix, y)), [want], rtol=1e-5)


def test_cluster_density_is_a_gaussian_per_cluster():
  rng = np.random.default_rng(4)
  points = rng.normal(size=(2, 10, 1, 2)) + np.array([0.0, 3.0])
  labels = np.tile(np.array([0] * 7 + [1] * 3), (2, 1))
  points[:, 7:] += 5.0  # cluster 1 elsewhere
  dist = WeightedSamples.uniform(jnp.asarray(points, jnp.float32))
  rule = (1.5, 0.2, 0.1)
  y = np.array([[1.0, 3.5], [4.0, 7.0]])
  want = []
  for m in range(2):
    p = 0.0
    for k, share in ((0, 0.7), (1, 0.3)):
      member = points[m, labels[m] == k, 0]
      mu, sd = member.mean(0), member.std(0)  # maximum-likelihood spread
      h = np.sqrt((rule[0] * sd) ** 2 + np.array(rule[1:]) ** 2)
      p += share * np.exp(-0.5 * np.sum(((y[m] - mu) / h) ** 2)) / (2 * math.pi * h.prod())
    want.append(-math.log(p))
  mix = regions.at_horizon(dist, 0, rule, labels)
  np.testing.assert_allclose(np.asarray(regions.nll(mix, y)), want, rtol=1e-4)


def _gaussian_sets(rng, scales, n):
  """Per scenario n samples and one truth from N(0, s^2 I), s = scales (M,) -> (M, n, 1, 2),
  (M, 1, 2)."""
  m = len(scales)
  samples = rng.normal(size=(m, n, 1, 2)) * scales[:, None, None, None]
  return samples.astype(np.float32), (rng.normal(size=(m, 1, 2)) * scales[:, None, None])


def test_kernel_density_of_gaussian_samples_is_the_convolved_gaussian():
  """Samples of N(0, s^2 I) under widths c sd (sd their own spread): for many samples the
  density is N(0, (s^2 + c^2 sd^2) I), NLL = log(2 pi v) + r^2 / (2 v), v = s^2 + c^2 sd^2."""
  rng = np.random.default_rng(2)
  scales = np.geomspace(0.2, 5.0, 200)
  samples, gt = _gaussian_sets(rng, scales, 4000)
  dist = WeightedSamples.uniform(jnp.asarray(samples))
  c = 0.7
  got = np.asarray(regions.nll(regions.at_horizon(dist, 0, (c, 1e-3, 1e-3)), gt[:, 0]))
  var = scales**2 + (c * samples.std(axis=(1, 2, 3))) ** 2  # the kernels use the samples' sd
  want = np.log(2 * math.pi * var) + np.sum(gt[:, 0] ** 2, -1) / (2 * var)
  assert abs(np.mean(got) - np.mean(want)) < 0.02
  assert np.median(np.abs(got - want)) < 0.03


def test_val_chosen_spread_rule_beats_one_width_when_scales_vary():
  """Scenarios whose spreads differ 25-fold: the rule chosen on val scores within 0.15 nats of
  the true density on fresh scenarios and clearly better than the best single width."""
  rng = np.random.default_rng(3)
  scales = np.geomspace(0.2, 5.0, 300)
  val_s, val_y = _gaussian_sets(rng, scales, 64)
  test_s, test_y = _gaussian_sets(rng, scales, 64)
  grid, scales_grid = tuple(np.geomspace(0.02, 10.0, 16)), (0.0, 0.25, 0.5, 1.0)
  rule = regions.choose_bandwidth(
      WeightedSamples.uniform(jnp.asarray(val_s)), val_y, 0, grid, scales_grid
  )
  fixed = regions.choose_bandwidth(
      WeightedSamples.uniform(jnp.asarray(val_s)), val_y, 0, grid, (0.0,)
  )
  test = WeightedSamples.uniform(jnp.asarray(test_s))
  score = lambda r: float(np.mean(regions.nll(regions.at_horizon(test, 0, r), test_y[:, 0])))
  true = float(
      np.mean(np.log(2 * math.pi * scales**2) + np.sum(test_y[:, 0] ** 2, -1) / (2 * scales**2))
  )
  assert rule[0] > 0.0
  assert score(rule) - true < 0.15
  assert score(fixed) - score(rule) > 0.3


def test_val_chosen_cluster_rule_approaches_the_true_mixture():
  """Two clusters per scenario (shares 0.7 / 0.3, 4 m apart, spreads varying 10-fold): the
  Gaussian-per-cluster rule chosen on val scores within 0.15 nats of the true mixture on
  fresh scenarios, and better than kernels on the points that ignore the clusters."""
  rng = np.random.default_rng(5)
  m, n = 300, 64
  scales = np.geomspace(0.2, 2.0, m)[:, None, None]
  labels = (np.arange(n) >= 0.7 * n).astype(np.int32)[None].repeat(m, 0)
  centre = np.stack([np.zeros(n), 4.0 * labels[0]], -1)  # (n, 2)

  def draw():
    points = centre + rng.normal(size=(m, n, 2)) * scales
    truth_label = rng.uniform(size=m) < 0.3
    y = np.stack([np.zeros(m), 4.0 * truth_label], -1) + rng.normal(size=(m, 2)) * scales[:, 0]
    return WeightedSamples.uniform(jnp.asarray(points[:, :, None], jnp.float32)), y[:, None]

  (val, val_y), (test, test_y) = draw(), draw()
  grid, cs = tuple(np.geomspace(0.02, 5.0, 12)), (0.0, 0.5, 1.0, 1.5)
  cluster = regions.choose_bandwidth(val, val_y, 0, grid, cs, labels=labels)
  kernel = regions.choose_bandwidth(val, val_y, 0, grid, cs)
  score = lambda r, lab: float(
      np.mean(regions.nll(regions.at_horizon(test, 0, r, lab), test_y[:, 0]))
  )
  s2 = scales[:, 0, 0] ** 2
  d2 = lambda c: np.sum((test_y[:, 0] - np.array([0.0, c])) ** 2, -1)
  true = -np.mean(
      np.log(
          (0.7 * np.exp(-d2(0.0) / (2 * s2)) + 0.3 * np.exp(-d2(4.0) / (2 * s2)))
          / (2 * math.pi * s2)
      )
  )
  assert score(cluster, labels) - true < 0.15
  assert score(cluster, labels) < score(kernel, None)


def test_wide_tail_is_the_hand_worked_mixture():
  """Rule (c, f_lon, f_lat, eps, lam): (1 - eps) x the kernels + eps x N(mean of the points,
  lam^2 (c^2 sd_all^2 + f^2)) per axis."""
  points = jnp.asarray([[[[0.0, 1.0]], [[2.0, 1.0]]]])  # lon: mean 1.5, sd sqrt(0.75)
  dist = WeightedSamples(points, jnp.asarray([[0.25, 0.75]]))
  rule = (2.0, 0.5, 0.3, 0.1, 10.0)
  mix = regions.at_horizon(dist, 0, rule)
  h_lon, h_lat = math.sqrt(4.0 * 0.75 + 0.25), 0.3
  gauss = lambda dx, dy, sx, sy: math.exp(-0.5 * ((dx / sx) ** 2 + (dy / sy) ** 2)) / (
      2 * math.pi * sx * sy
  )
  y = np.array([[9.0, -2.0]])
  kernels = 0.25 * gauss(9.0, -3.0, h_lon, h_lat) + 0.75 * gauss(7.0, -3.0, h_lon, h_lat)
  want = -math.log(0.9 * kernels + 0.1 * gauss(7.5, -3.0, 10 * h_lon, 10 * h_lat))
  np.testing.assert_allclose(np.asarray(regions.nll(mix, y)), [want], rtol=1e-5)
  np.testing.assert_allclose(np.asarray(mix.weights).sum(), 1.0, rtol=1e-6)
  no_tail = regions.at_horizon(dist, 0, rule[:3] + (0.0, 10.0))
  np.testing.assert_array_equal(np.asarray(no_tail.means), np.asarray(points[:, :, 0]))


def test_val_chosen_tail_pays_off_when_the_truth_leaves_the_samples():
  """Samples of N(0, I) while 5 % of truths lie 8 m away: val picks a tail (eps > 0), which
  lowers the NLL of fresh scenarios by more than 0.3 nats; without outliers whatever it
  picks costs fresh scenarios less than 0.02 nats."""
  rng = np.random.default_rng(6)
  m, n = 400, 64

  def draw(outliers):
    samples = rng.normal(size=(m, n, 1, 2)).astype(np.float32)
    y = rng.normal(size=(m, 1, 2)) + outliers * (rng.uniform(size=(m, 1, 1)) < 0.05) * 8.0
    return WeightedSamples.uniform(jnp.asarray(samples)), y

  grid, cs = tuple(np.geomspace(0.05, 2.0, 8)), (0.0, 0.5, 1.0)
  (val, val_y), (test, test_y) = draw(1.0), draw(1.0)
  rule = regions.choose_bandwidth(val, val_y, 0, grid, cs)
  plain = regions.choose_bandwidth(val, val_y, 0, grid, cs, tails=((0.0,), (3.0,)))
  score = lambda r: float(np.mean(regions.nll(regions.at_horizon(test, 0, r), test_y[:, 0])))
  assert rule[3] > 0.0
  assert score(plain) - score(rule) > 0.3
  (clean, clean_y), (fresh, fresh_y) = draw(0.0), draw(0.0)
  clean_score = lambda r: float(
      np.mean(regions.nll(regions.at_horizon(fresh, 0, r), fresh_y[:, 0]))
  )
  with_tail = regions.choose_bandwidth(clean, clean_y, 0, grid, cs)
  without = regions.choose_bandwidth(clean, clean_y, 0, grid, cs, tails=((0.0,), (3.0,)))
  assert clean_score(with_tail) - clean_score(without) < 0.02


def test_mixture_at_horizon_is_its_exact_density():
  rng = np.random.default_rng(0)
  gm = GaussianMixture(
      jnp.asarray(rng.normal(size=(2, 3, 4, 2))),
      jnp.asarray(rng.uniform(0.5, 2.0, (2, 3, 4, 2))),
      jnp.asarray([[0.2, 0.3, 0.5], [0.6, 0.2, 0.2]]),
  )
  y = jnp.asarray(rng.normal(size=(2, 4, 2)))
  np.testing.assert_allclose(
      np.asarray(regions.nll(regions.at_horizon(gm, 2), y[:, 2])),
      -np.asarray(gm.log_density(y))[:, 2],
      rtol=1e-5,
  )


def test_point_mass_bandwidth_recovers_the_error_spread():
  rng = np.random.default_rng(1)
  gt = rng.normal(size=(4000, 1, 2)) * np.array([2.0, 0.5])
  dist = WeightedSamples.point_mass(jnp.zeros((4000, 1, 2)))
  c, lon, lat, eps, _ = regions.choose_bandwidth(dist, gt, 0, scales=(0.0, 0.5, 1.0))
  assert eps == 0.0  # Gaussian errors: no tail pays for its weight
  assert c == 0.0  # a point mass has no spread: every c ties, the smallest is taken
  grid = np.asarray(regions.BANDWIDTH_GRID_M)
  nearest = lambda s: grid[np.argmin(np.abs(np.log(grid / s)))]
  assert abs(math.log(lon / nearest(2.0))) < 0.3 and abs(math.log(lat / nearest(0.5))) < 0.3


def test_hdr_of_a_gaussian_is_the_disc():
  """N(0, s^2 I): u = 1 - exp(-r^2 / (2 s^2)), area of level a = 2 pi s^2 (-log(1 - a))."""
  s, m = 1.5, 300
  mix = regions.HorizonMixture(jnp.zeros((m, 1, 2)), jnp.full((m, 1, 2), s), jnp.ones((m, 1)))
  r = np.linspace(0.1, 4.0, m)
  y = np.stack([r, np.zeros(m)], 1)
  u, area = regions.hdr(jax.random.key(0), mix, y, (0.5, 0.9))
  np.testing.assert_allclose(u, 1 - np.exp(-(r**2) / (2 * s * s)), atol=0.1)
  want = 2 * math.pi * s * s * -np.log(1 - np.array([0.5, 0.9]))
  np.testing.assert_allclose(area.mean(0), want, rtol=0.05)
