"""Schedule, parameterisation round trips, loss."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax import diffusion


def test_cosine_schedule_closed_form():
  s = diffusion.cosine_schedule(1000)
  f = lambda u: math.cos((u + 0.008) / 1.008 * math.pi / 2) ** 2
  # abar_t = f((t+1)/T) / f(0) wherever beta is not clipped.
  for t in (0, 10, 500, 900):
    np.testing.assert_allclose(float(s.alphas_cumprod[t]), f((t + 1) / 1000) / f(0), rtol=1e-5)
  assert np.all(np.diff(np.asarray(s.alphas_cumprod)) < 0)
  assert float(s.betas.max()) <= 0.999 + 1e-7
  assert s.num_steps == 1000


def test_ddim_timesteps_linear():
  ts = diffusion.ddim_timesteps(1000, 10)
  assert ts[0] == 999 and ts[-1] == 0 and len(ts) == 10
  np.testing.assert_allclose(np.diff(ts), -111, atol=1)
  np.testing.assert_array_equal(diffusion.ddim_timesteps(1000, 1000), np.arange(999, -1, -1))


def test_round_trips():
  k1, k2 = jax.random.split(jax.random.key(0))
  x0 = jax.random.normal(k1, (6, 125, 2))
  eps = jax.random.normal(k2, (6, 125, 2))
  abar = jnp.linspace(0.05, 0.95, 6)
  x_t = diffusion.q_sample(x0, eps, abar)
  v = diffusion.v_from_x0_eps(x0, eps, abar)
  np.testing.assert_allclose(diffusion.x0_from_v(x_t, v, abar), x0, atol=1e-5)
  np.testing.assert_allclose(diffusion.eps_from_v(x_t, v, abar), eps, atol=1e-5)
  np.testing.assert_allclose(diffusion.v_from_eps(x_t, eps, abar), v, atol=1e-4)
  np.testing.assert_allclose(diffusion.eps_from_x0(x_t, x0, abar), eps, atol=1e-4)
  # by hand for one element
  a, s = math.sqrt(abar[2]), math.sqrt(1 - abar[2])
  np.testing.assert_allclose(v[2, 0, 0], a * eps[2, 0, 0] - s * x0[2, 0, 0], rtol=1e-5)


def test_v_loss_zero_for_oracle_and_drops_condition():
  schedule = diffusion.cosine_schedule(1000)
  x0 = jnp.ones((512, 8, 2)) * 0.3
  seen = []

  def oracle(x_t, t, cond):  # exact v for the point mass x0 = 0.3
    abar = schedule.alphas_cumprod[t][:, None, None]
    eps = (x_t - jnp.sqrt(abar) * 0.3) / jnp.sqrt(1 - abar)
    seen.append(cond)
    return jnp.sqrt(abar) * eps - jnp.sqrt(1 - abar) * 0.3

  loss = diffusion.v_loss(
      oracle,
      x0,
      jnp.zeros(512, jnp.int32),
      jax.random.key(0),
      schedule,
      null_cond=7,
      cond_drop_prob=0.25,
  )
  assert float(loss) < 1e-8
  share = float(jnp.mean(seen[0] == 7))
  assert 0.18 < share < 0.32
  zero = lambda x_t, t, c: jnp.zeros_like(x_t)
  w = jnp.concatenate([jnp.ones(256), jnp.zeros(256)])
  full = diffusion.v_loss(
      zero, x0, jnp.zeros(512, jnp.int32), jax.random.key(1), schedule, null_cond=7
  )
  half = diffusion.v_loss(
      zero, x0, jnp.zeros(512, jnp.int32), jax.random.key(1), schedule, null_cond=7, weight=w
  )
  assert float(full) > 0.5 and abs(float(half) - float(full)) < 0.2
