"""DPM-Solver++(2M) against the exact probability-flow ODE map of Gaussian data."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import diffusion
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.diffusion import solvers
from tests.diffusion.gaussian_data import MU, STD, gaussian_v
from tests.models import tiny_nets


@pytest.fixture(scope="module")
def schedule():
  return diffusion.cosine_schedule(1000)


def _exact_x0(x_T, abar_T):
  """The PF-ODE keeps each point's standard score: x0 = MU + STD (x_T - m_T) / s_T."""
  m_T = np.sqrt(abar_T) * MU
  s_T = np.sqrt(abar_T * STD**2 + 1.0 - abar_T)
  return MU + STD * (x_T - m_T) / s_T


def _error(schedule, steps):
  """Max |DPM-Solver++(2M) - exact ODE map| over a batch of x_T."""
  v_fn = lambda x, t: gaussian_v(x, t, schedule.alphas_cumprod)
  x_T = jax.random.normal(jax.random.key(0), (256, 4, 2))
  exact = _exact_x0(np.asarray(x_T, np.float64), float(schedule.alphas_cumprod[-1]))
  dpm = solvers.dpmpp_2m_sample(v_fn, None, x_T.shape, schedule, steps=steps, x_T=x_T)
  return float(np.abs(np.asarray(dpm, np.float64) - exact).max())


def test_timesteps_descend_from_T_and_skip_zero():
  for steps in (1, 2, 3, 5, 10, 20, 999):
    ts = solvers.solver_timesteps(1000, steps)
    assert ts.shape == (steps,) and ts[0] == 999 and ts[-1] > 0
    assert np.all(np.diff(ts) < 0)
  np.testing.assert_array_equal(solvers.solver_timesteps(1000, 4), [999, 749, 500, 250])
  with pytest.raises(ValueError, match="steps"):
    solvers.solver_timesteps(1000, 1000)


def test_one_step_is_the_predicted_x0(schedule):
  v_fn = lambda x, t: gaussian_v(x, t, schedule.alphas_cumprod)
  x_T = jax.random.normal(jax.random.key(3), (8, 4, 2))
  abar = schedule.alphas_cumprod[-1]
  expected = jnp.sqrt(abar) * x_T - jnp.sqrt(1 - abar) * v_fn(x_T, jnp.full((8,), 999))
  out = solvers.dpmpp_2m_sample(v_fn, None, x_T.shape, schedule, steps=1, x_T=x_T)
  np.testing.assert_allclose(out, expected, atol=1e-6)


def test_second_order_convergence_to_the_exact_ode_map(schedule):
  e25, e50, e100 = (_error(schedule, s) for s in (25, 50, 100))
  # second order: halving the step size divides the error by about 4 (DDIM: 2)
  assert e50 < e25 / 3.0 and e100 < e50 / 3.0, (e25, e50, e100)


def test_beats_ddim_at_equal_network_evaluations(schedule):
  v_fn = lambda x, t: gaussian_v(x, t, schedule.alphas_cumprod)
  key = jax.random.key(7)
  for steps in (3, 5, 10, 20):
    # both draw x_T from fold_in(key, steps)
    x_T = jax.random.normal(jax.random.fold_in(key, steps), (512, 4, 2))
    exact = _exact_x0(np.asarray(x_T, np.float64), float(schedule.alphas_cumprod[-1]))
    dpm = solvers.dpmpp_2m_sample(v_fn, key, x_T.shape, schedule, steps=steps)
    ddim = diffusion.ddim_sample(v_fn, key, x_T.shape, schedule, steps=steps)
    err_dpm = np.abs(np.asarray(dpm) - exact).mean()
    err_ddim = np.abs(np.asarray(ddim) - exact).mean()
    assert err_dpm < (0.85 if steps < 10 else 0.6) * err_ddim, (steps, err_dpm, err_ddim)


def test_reproduces_gaussian_moments(schedule):
  v_fn = lambda x, t: gaussian_v(x, t, schedule.alphas_cumprod)
  x = solvers.dpmpp_2m_sample(v_fn, jax.random.key(2), (4096, 16, 2), schedule, steps=100)
  x = np.asarray(x).reshape(-1, 2)
  np.testing.assert_allclose(x.mean(0), MU, atol=0.02)
  np.testing.assert_allclose(x.std(0), STD, rtol=0.02)


def test_clip_bounds_every_predicted_x0(schedule):
  v_fn = lambda x, t: 5.0 * gaussian_v(x, t, schedule.alphas_cumprod)
  out = solvers.dpmpp_2m_sample(v_fn, jax.random.key(4), (64, 4, 2), schedule, steps=1, clip_x0=1.0)
  assert np.abs(np.asarray(out)).max() <= 1.0 + 1e-6


def _tiny_unet():
  from cvmdx_jax.models import unet1d

  cfg = tiny_nets.unet_config(4)
  g, p = unet1d.init_unet(cfg, jax.random.key(0))
  p = jax.tree.map(lambda a: a + 0.02 * jax.random.normal(jax.random.key(1), a.shape), p)
  return cfg, g, p


@pytest.mark.slow
def test_predict_batch_with_dpmpp2m_matches_many_step_ddim():
  """sampler="dpmpp2m" runs through predict_batch and, at many steps, lands where
  many-step DDIM does: both integrate the same guided probability-flow ODE."""
  from cvmdx_jax.inference import sampling
  from tests.inference.denoisers import bundle

  cfg, g, p = _tiny_unet()
  predict = jax.jit(sampling.predict_batch, static_argnames=sampling.STATIC_ARGNAMES)
  b = 2
  keys = jax.random.split(jax.random.key(5), b)

  def run(sampler, steps):
    config = SamplingConfig(num_samples=3, sampler=sampler, steps=steps, clip_x0=None)
    return predict(
        bundle(g, p, cfg),
        jnp.arange(b),
        jnp.array([5.0, 40.0]),
        jnp.full(b, 30.0),
        jnp.zeros(b),
        keys,
        schedule=diffusion.cosine_schedule(),
        config=config,
    ).controls

  few = run("dpmpp2m", 4)
  assert few.shape == (b, 3, 125, 2) and bool(jnp.all(jnp.isfinite(few)))
  dpm, ddim = run("dpmpp2m", 200), run("ddim", 200)
  coarse = run("ddim", 4)
  scale = float(jnp.abs(ddim).mean())
  err = float(jnp.abs(dpm - ddim).mean())
  assert err < 0.02 * scale, (err, scale)
  # and the test has teeth: a 4-step DDIM is much farther from the ODE's end point
  assert float(jnp.abs(coarse - ddim).mean()) > 5 * err


def test_unknown_sampler_is_refused():
  with pytest.raises(ValueError, match="sampling.sampler"):
    SamplingConfig(sampler="unipc")
