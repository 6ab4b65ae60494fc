"""Higher-order solvers of the (guided) probability-flow ODE, beyond the paper.

DPM-Solver++(2M) (Lu et al. 2022, "DPM-Solver++", Algorithm 2) in data (x0)
prediction form, with alpha_t = sqrt(abar_t), sigma_t = sqrt(1 - abar_t) and
lambda_t = log(alpha_t / sigma_t):

  x_{i+1} = (sigma_{i+1} / sigma_i) x_i - alpha_{i+1} (exp(-h) - 1) D_i,
  h = lambda_{i+1} - lambda_i,
  D_i = (1 + 1/(2r)) x0_i - 1/(2r) x0_{i-1},  r = h_{i-1} / h  (second order),
  D_i = x0_i on the first and the last step (first order = DDIM).

S network evaluations at S timesteps t_0 = T-1 > ... > t_{S-1}; the last update
goes to abar = 1 (sigma = 0), where it returns the predicted x0. Unlike DDIM's
grid (which ends with an evaluation at t = 0 that changes almost nothing), no
evaluation is spent on an already clean sample.
"""

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.diffusion.samplers import predict_x0_eps
from cvmdx_jax.diffusion.schedule import Schedule
from cvmdx_jax.errors import UserError


def solver_timesteps(num_steps: int, steps: int) -> np.ndarray:
  """S integer timesteps t_i = round((T-1) (1 - i/S)), descending from T-1, for a solver
  whose last update goes to abar = 1 (so t = 0 itself is never evaluated).

  Returns:
    (S,) int32, strictly decreasing.
  """
  if not 1 <= steps < num_steps:
    raise UserError(f"solver steps must be in [1, {num_steps - 1}], got {steps}")
  return np.round(np.linspace(num_steps - 1, 0, steps + 1)[:steps]).astype(np.int32)


def dpmpp_2m_coefficients(abar_s: jax.Array, abar_t: jax.Array):
  """Per-step coefficients of DPM-Solver++(2M).

  Args:
    abar_s: (S,) abar at the evaluation timesteps.
    abar_t: (S,) abar at the step targets (abar_s[1:] then 1).

  Returns:
    (ratio, coef, c_cur, c_prev), each (S,): x_next = ratio x + coef D with
    D = c_cur x0_i + c_prev x0_{i-1}.
  """
  steps = abar_s.shape[0]
  lam_s = 0.5 * (jnp.log(abar_s) - jnp.log1p(-abar_s))
  final = jnp.arange(steps) == steps - 1
  safe_t = jnp.where(final, 0.5, abar_t)
  lam_t = 0.5 * (jnp.log(safe_t) - jnp.log1p(-safe_t))
  h = lam_t - lam_s
  ratio = jnp.where(final, 0.0, jnp.sqrt((1.0 - safe_t) / (1.0 - abar_s)))
  coef = jnp.where(final, 1.0, -jnp.sqrt(safe_t) * jnp.expm1(-h))
  h_prev = jnp.concatenate([h[:1], h[:-1]])
  second = (jnp.arange(steps) > 0) & ~final
  half_inv_r = jnp.where(second, h / (2.0 * h_prev), 0.0)
  return ratio, coef, 1.0 + half_inv_r, -half_inv_r


def dpmpp_2m_sample(
    v_fn,
    key,
    shape,
    schedule: Schedule,
    steps: int = 5,
    clip_x0: float | None = None,
    x_T: jax.Array | None = None,
):
  """DPM-Solver++(2M) from noise to x0 in `steps` network evaluations.

  Args:
    v_fn: (x_t, t) -> v, as for the other samplers (guidance composed in).
    key: PRNG key for x_T = N(0, I) (fold_in(key, steps), as DDIM); unused if x_T given.
    shape: sample shape, leading dim = batch.
    schedule: the training `Schedule`.
    steps: S network evaluations.
    clip_x0: clip each predicted x0 to [-clip_x0, clip_x0] (None: no clip).
    x_T: optional initial noise of `shape`.

  Returns:
    x0 samples of `shape`.
  """
  ts = jnp.asarray(solver_timesteps(schedule.num_steps, steps))
  abar = schedule.alphas_cumprod
  abar_s = abar[ts]
  abar_t = jnp.concatenate([abar_s[1:], jnp.ones((1,), abar.dtype)])
  coefs = dpmpp_2m_coefficients(abar_s, abar_t)
  if x_T is None:
    x_T = jax.random.normal(jax.random.fold_in(key, steps), shape)

  def body(carry, inputs):
    x, x0_prev = carry
    t, a_s, ratio, coef, c_cur, c_prev = inputs
    x0, _ = predict_x0_eps(v_fn, x, t, a_s, clip_x0)
    x_next = ratio * x + coef * (c_cur * x0 + c_prev * x0_prev)
    return (x_next, x0), None

  (x0, _), _ = jax.lax.scan(body, (x_T, jnp.zeros_like(x_T)), (ts, abar_s, *coefs))
  return x0
