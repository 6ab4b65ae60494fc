"""DDIM and DDPM samplers over any v-prediction function, as `lax.scan` loops.

`v_fn(x_t, t)` takes x_t of `shape` and integer timesteps t (shape[0],) and
returns the v-prediction. Keys: step i uses `fold_in(key, i)`; the initial noise
uses `fold_in(key, S)` (DDIM) or `fold_in(key, T)` (DDPM), so all draws differ,
unless an explicit `x_T` is given.

`ddim_sample` / `ddpm_sample` follow the paper; `official_ddim_sample` is the
guided DDIM loop of the official cVMDx code, update for update (`sampling.mode`).
"""

import jax
import jax.numpy as jnp

from cvmdx_jax.diffusion import param
from cvmdx_jax.diffusion.guidance import official_step_weights
from cvmdx_jax.diffusion.schedule import Schedule, ddim_timesteps, official_ddim_timesteps


def predict_x0_eps(v_fn, x_t, t, abar_t, clip_x0):
  """x0 and eps from v_fn at timestep t (a scalar, or (B,) with abar_t (B,)); x0
  optionally clipped (eps then recomputed from the clipped x0)."""
  t_vec = jnp.broadcast_to(jnp.asarray(t, jnp.int32), (x_t.shape[0],))
  v = v_fn(x_t, t_vec)
  x0 = param.x0_from_v(x_t, v, abar_t)
  if clip_x0 is None:
    return x0, param.eps_from_v(x_t, v, abar_t)
  x0 = jnp.clip(x0, -clip_x0, clip_x0)
  return x0, param.eps_from_x0(x_t, x0, abar_t)


def initial_noise(key, index: int, shape, x_T):
  """x_T if given (its shape checked), else N(0, I) of `shape` from fold_in(key, index)."""
  if x_T is None:
    return jax.random.normal(jax.random.fold_in(key, index), shape)
  if tuple(x_T.shape) != tuple(shape):
    raise ValueError(f"x_T has shape {tuple(x_T.shape)}, expected {tuple(shape)}")
  return x_T


def ddim_sample(
    v_fn,
    key,
    shape,
    schedule: Schedule,
    steps: int = 10,
    eta: float = 0.0,
    clip_x0: float | None = None,
    x_T=None,
):
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
    x_T: the initial noise of `shape` (None: drawn from `key`).

  Returns:
    x0 samples of `shape`.
  """
  ts = jnp.asarray(ddim_timesteps(schedule.num_steps, steps))
  abar = schedule.alphas_cumprod
  abar_prev = jnp.concatenate([abar[ts[1:]], jnp.ones((1,), abar.dtype)])
  x_T = initial_noise(key, steps, shape, x_T)

  def body(x_t, inputs):
    i, t, a_prev = inputs
    a_t = abar[t]
    x0, eps = predict_x0_eps(v_fn, x_t, t, a_t, clip_x0)
    sigma = eta * jnp.sqrt((1.0 - a_prev) / (1.0 - a_t) * (1.0 - a_t / a_prev))
    noise = jax.random.normal(jax.random.fold_in(key, i), shape)
    x_prev = (
        jnp.sqrt(a_prev) * x0
        + jnp.sqrt(jnp.maximum(1.0 - a_prev - sigma**2, 0.0)) * eps
        + sigma * noise
    )
    return x_prev, None

  x0, _ = jax.lax.scan(body, x_T, (jnp.arange(steps), ts, abar_prev))
  return x0


def ddpm_sample(v_fn, key, shape, schedule: Schedule, clip_x0: float | None = None, x_T=None):
  """Ancestral DDPM (Ho et al. 2020) over all T steps with the posterior
  q(x_{t-1} | x_t, x0): mean = c1 x0 + c2 x_t, variance beta~_t
  = beta_t (1 - abar_{t-1}) / (1 - abar_t); no noise at t = 0. `x_T` as in DDIM.
  """
  num_steps = schedule.num_steps
  abar = schedule.alphas_cumprod
  betas = schedule.betas
  abar_prev = jnp.concatenate([jnp.ones((1,), abar.dtype), abar[:-1]])
  x_T = initial_noise(key, num_steps, shape, x_T)

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


def _rounded(p):
  """`p` itself (NaN stays NaN) as a value of its own: XLA's CPU backend may contract
  `a * b + c` into one fused multiply-add, rounding once where the official code (one
  PyTorch kernel per operation) rounds twice. At t = 999 the official x0 divides a
  float32 cancellation by alpha = 5e-5, so one ulp there moves x0 by up to 5e-3."""
  return jnp.where(jnp.isnan(p), jnp.nan, p)


def official_ddim_sample(
    branches_fn,
    key,
    shape,
    schedule: Schedule,
    steps: int = 10,
    eta: float = 0.0,
    clip_x0: float | None = 1.0,
    w_start: float = 0.1,
    w_end: float = 1.0,
    x_T=None,
):
  """The official cVMDx guided DDIM loop (`ddim_sample_loop`, v-prediction), float32
  operation for operation.

  Grid `official_ddim_timesteps` (steps = 10: 9 updates 999 -> 888 -> ... -> 111 -> 0);
  update i uses the weight w_i of `official_step_weights(steps - 1, w_start, w_end)`
  (no delta: the official loop does not use it). With alpha_t = sqrt(abar_t),
  sigma_t = sqrt(1 - abar_t), abar_prev = alphas_cumprod[t_prev]:
    eps_c, eps_u = sigma_t x_t + alpha_t v_c, sigma_t x_t + alpha_t v_u
    eps = eps_u + w_i (eps_c - eps_u)
    x0 = clip((x_t - sigma_t eps) / alpha_t)          (x0 clipped, eps not)
    x_prev = sqrt(abar_prev) x0 + sqrt(max(1 - abar_prev - s^2, 0)) eps + [t_prev > 0] s z
  with s = eta sqrt((1 - abar_prev) / (1 - abar_t)) sqrt(1 - abar_t / abar_prev). The
  last update goes to alphas_cumprod[0] (not 1); its x_prev, unclipped, is the result.

  Args:
    branches_fn: (x_t, t) -> (v_cond, v_uncond), e.g. `guidance.cond_uncond_v_fn`.
    key: PRNG key (noise of eta > 0 and, without x_T, the initial noise).
    shape: sample shape, leading dim = batch.
    schedule: the training `Schedule`.
    steps: the official `ddim_steps` (grid points including t = 0; steps - 1 updates).
    eta: DDIM noise.
    clip_x0: clip x0 to [-clip_x0, clip_x0] (official clip_denoised: 1); None: no clip.
    w_start, w_end: guidance weight at the first and the last update (official 0.1, 1).
    x_T: the initial noise of `shape` (None: drawn from `key`).

  Returns:
    samples of `shape`.
  """
  ts, ts_prev = official_ddim_timesteps(schedule.num_steps, steps)
  weights = official_step_weights(len(ts), w_start, w_end)
  abar = schedule.alphas_cumprod
  x_T = initial_noise(key, steps, shape, x_T)

  def body(x_t, inputs):
    i, t, t_prev, w = inputs
    a_t, a_prev = abar[t], abar[t_prev]
    alpha, sigma_t = _rounded(jnp.sqrt(a_t)), _rounded(jnp.sqrt(1.0 - a_t))
    v_c, v_u = branches_fn(x_t, jnp.full((x_t.shape[0],), t, jnp.int32))
    sx = _rounded(sigma_t * x_t)
    eps_u = sx + _rounded(alpha * v_u)
    eps = eps_u + _rounded(w * ((sx + _rounded(alpha * v_c)) - eps_u))
    x0 = (x_t - _rounded(sigma_t * eps)) / alpha
    if clip_x0 is not None:
      x0 = jnp.clip(x0, -clip_x0, clip_x0)
    s = eta * jnp.sqrt((1.0 - a_prev) / (1.0 - a_t)) * jnp.sqrt(1.0 - a_t / a_prev)
    noise = jax.random.normal(jax.random.fold_in(key, i), shape)
    x_prev = _rounded(jnp.sqrt(a_prev) * x0) + _rounded(
        jnp.sqrt(jnp.maximum(1.0 - a_prev - s**2, 0.0)) * eps
    )
    return x_prev + _rounded(jnp.where(t_prev > 0, s, 0.0) * noise), None

  out, _ = jax.lax.scan(
      body, x_T, (jnp.arange(len(ts)), jnp.asarray(ts), jnp.asarray(ts_prev), jnp.asarray(weights))
  )
  return out
