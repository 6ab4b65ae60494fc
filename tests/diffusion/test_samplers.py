"""Samplers against the exact v-predictor of Gaussian data and a numpy DDIM loop."""

import jax
import numpy as np
import pytest

from cvmdx_jax import diffusion
from tests.diffusion.gaussian_data import MU, STD, gaussian_v


@pytest.fixture(scope="module")
def schedule():
  return diffusion.cosine_schedule(1000)


def _v_fn(schedule):
  return lambda x_t, t: gaussian_v(x_t, t, schedule.alphas_cumprod)


def _check_moments(x, tol=0.02):
  x = np.asarray(x).reshape(-1, 2)
  np.testing.assert_allclose(x.mean(0), MU, atol=tol * np.abs(MU).max())
  np.testing.assert_allclose(x.std(0), STD, rtol=tol)


def test_ddpm_reproduces_gaussian(schedule):
  sample = jax.jit(lambda k: diffusion.ddpm_sample(_v_fn(schedule), k, (4096, 16, 2), schedule))
  _check_moments(sample(jax.random.key(0)))


def test_ddim_many_steps_reproduces_gaussian(schedule):
  sample = jax.jit(
      lambda k: diffusion.ddim_sample(_v_fn(schedule), k, (4096, 16, 2), schedule, steps=200)
  )
  _check_moments(sample(jax.random.key(1)))


def _numpy_ddim(x_T, abar_table, ts, eta=0.0, noises=None):
  x = x_T.astype(np.float64)
  abar_table = np.asarray(abar_table, np.float64)
  for i, t in enumerate(ts):
    a_t = abar_table[t]
    a_prev = abar_table[ts[i + 1]] if i + 1 < len(ts) else 1.0
    alpha, sigma = np.sqrt(a_t), np.sqrt(1 - a_t)
    var = alpha**2 * STD**2 + sigma**2
    c = x - alpha * MU
    v = alpha * (sigma / var * c) - sigma * (MU + alpha * STD**2 / var * c)
    x0 = alpha * x - sigma * v
    eps = sigma * x + alpha * v
    s = eta * np.sqrt((1 - a_prev) / (1 - a_t) * (1 - a_t / a_prev))
    x = np.sqrt(a_prev) * x0 + np.sqrt(max(1 - a_prev - s**2, 0.0)) * eps
    if noises is not None:
      x = x + s * noises[i]
  return x


def test_ddim_10_steps_matches_numpy_loop(schedule):
  key = jax.random.key(2)
  shape = (64, 125, 2)
  out = jax.jit(lambda k: diffusion.ddim_sample(_v_fn(schedule), k, shape, schedule, steps=10))(key)
  x_T = np.asarray(jax.random.normal(jax.random.fold_in(key, 10), shape))
  ts = list(range(999, -1, -111))
  assert ts == [int(t) for t in diffusion.ddim_timesteps(1000, 10)]
  ref = _numpy_ddim(x_T, schedule.alphas_cumprod, ts)
  np.testing.assert_allclose(np.asarray(out), ref, atol=2e-4)


def test_ddim_eta_one_matches_numpy_loop(schedule):
  key = jax.random.key(3)
  shape = (8, 125, 2)
  out = diffusion.ddim_sample(_v_fn(schedule), key, shape, schedule, steps=10, eta=1.0)
  x_T = np.asarray(jax.random.normal(jax.random.fold_in(key, 10), shape))
  noises = [np.asarray(jax.random.normal(jax.random.fold_in(key, i), shape)) for i in range(10)]
  ref = _numpy_ddim(
      x_T, schedule.alphas_cumprod, list(diffusion.ddim_timesteps(1000, 10)), eta=1.0, noises=noises
  )
  np.testing.assert_allclose(np.asarray(out), ref, atol=2e-4)


def test_ddim_clip_bounds_x0(schedule):
  wild = lambda x_t, t: -10.0 * x_t  # predicts x0 far outside [-1, 1]
  out = diffusion.ddim_sample(wild, jax.random.key(0), (4, 125, 2), schedule, steps=10, clip_x0=1.0)
  assert np.all(np.abs(np.asarray(out)) <= 1.0 + 1e-6)


def test_samplers_are_deterministic_under_a_key(schedule):
  f = lambda k: diffusion.ddim_sample(_v_fn(schedule), k, (4, 125, 2), schedule, steps=10)
  a, b, c = f(jax.random.key(5)), f(jax.random.key(5)), f(jax.random.key(6))
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  assert not np.allclose(np.asarray(a), np.asarray(c))
