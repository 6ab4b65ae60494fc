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
  mix = regions.at_horizon(dist, 0, bandwidth=(1.0, 0.5))
  y = np.array([[1.0, 0.5]])
  pdf = lambda mx: math.exp(-0.5 * ((1 - mx) ** 2 + 1.0)) / (2 * math.pi * 0.5)
  want = -math.log(0.25 * pdf(0.0) + 0.75 * pdf(2.0))
  np.testing.assert_allclose(np.asarray(regions.nll(mix, y)), [want], rtol=1e-5)


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
  lon, lat = regions.choose_bandwidth(dist, gt, 0)
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
