"""DDIM and DDPM samplers over any v-prediction function, as `lax.scan` loops.

`v_fn(x_t, t)` takes x_t of `shape` and integer timesteps t (shape[0],) and
returns the v-prediction. Keys: step i uses `fold_in(key, i)`; the initial noise
uses `fold_in(key, S)` (DDIM) or `fold_in(key, T)` (DDPM), so all draws differ.
"""

import jax
import jax.numpy as jnp

from cvmdx_jax.diffusion import param
from cvmdx_jax.diffusion.schedule import Schedule, ddim_timesteps


def predict_x0_eps(v_fn, x_t, t, abar_t, clip_x0):
  """x0 and eps from v_fn at the scalar timestep t; x0 optionally clipped (eps then
  recomputed from the clipped x0)."""
  t_vec = jnp.full((x_t.shape[0],), t, jnp.int32)
  v = v_fn(x_t, t_vec)
  x0 = param.x0_from_v(x_t, v, abar_t)
  if clip_x0 is None:
    return x0, param.eps_from_v(x_t, v, abar_t)
  x0 = jnp.clip(x0, -clip_x0, clip_x0)
  return x0, param.eps_from_x0(x_t, x0, abar_t)


def ddim_sample(v_fn, key, shape, schedule: Schedule, steps: int = 10, eta: float = 0.0,
                clip_x0: float | None = None):
  """DDIM (Song et al. 2021) over S linearly spaced timesteps.

  x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev - s^2) eps + s z,
  s = eta sqrt((1 - abar_prev) / (1 - abar_t)) sqrt(1 - abar_t / abar_prev);
  after the last step (t = 0) abar_prev = 1, so the result is x0.

  Args:
    v_fn: (x_t, t) -> v.
    key: PRNG key.
    shape: sample shape, leading dim = batch.
    schedule: the training `Schedule`.
    steps: S.
    eta: 0 = deterministic DDIM, 1 = DDPM-like noise.
    clip_x0: clip the predicted x0 to [-clip_x0, clip_x0] (None: no clip).

  Returns:
    x0 samples of `shape`.
  """
  ts = jnp.asarray(ddim_timesteps(schedule.num_steps, steps))
  abar = schedule.alphas_cumprod
  abar_prev = jnp.concatenate([abar[ts[1:]], jnp.ones((1,), abar.dtype)])
  x_T = jax.random.normal(jax.random.fold_in(key, steps), shape)

  def body(x_t, inputs):
    i, t, a_prev = inputs
    a_t = abar[t]
    x0, eps = predict_x0_eps(v_fn, x_t, t, a_t, clip_x0)
    sigma = eta * jnp.sqrt((1.0 - a_prev) / (1.0 - a_t) * (1.0 - a_t / a_prev))
    noise = jax.random.normal(jax.random.fold_in(key, i), shape)
    x_prev = (jnp.sqrt(a_prev) * x0 + jnp.sqrt(jnp.maximum(1.0 - a_prev - sigma**2, 0.0)) * eps
              + sigma * noise)
    return x_prev, None

  x0, _ = jax.lax.scan(body, x_T, (jnp.arange(steps), ts, abar_prev))
  return x0


def ddpm_sample(v_fn, key, shape, schedule: Schedule, clip_x0: float | None = None):
  """Ancestral DDPM (Ho et al. 2020) over all T steps with the posterior
  q(x_{t-1} | x_t, x0): mean = c1 x0 + c2 x_t, variance beta~_t
  = beta_t (1 - abar_{t-1}) / (1 - abar_t); no noise at t = 0.
  """
  num_steps = schedule.num_steps
  abar = schedule.alphas_cumprod
  betas = schedule.betas
  abar_prev = jnp.concatenate([jnp.ones((1,), abar.dtype), abar[:-1]])
  x_T = jax.random.normal(jax.random.fold_in(key, num_steps), shape)

  def body(x_t, t):
    a_t, a_prev, b_t = abar[t], abar_prev[t], betas[t]
    x0, _ = predict_x0_eps(v_fn, x_t, t, a_t, clip_x0)
    c1 = b_t * jnp.sqrt(a_prev) / (1.0 - a_t)
    c2 = (1.0 - a_prev) * jnp.sqrt(1.0 - b_t) / (1.0 - a_t)
    var = b_t * (1.0 - a_prev) / (1.0 - a_t)
    noise = jax.random.normal(jax.random.fold_in(key, t), shape)
    return c1 * x0 + c2 * x_t + jnp.where(t > 0, jnp.sqrt(var), 0.0) * noise, None

  x0, _ = jax.lax.scan(body, x_T, jnp.arange(num_steps - 1, -1, -1))
  return x0
