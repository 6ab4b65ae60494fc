"""Uncertainty-aware classifier-free guidance (paper, "Uncertainty-Aware CFG").

  w(t, delta) = w_min + (w_max(delta) - w_min) (1 - cos(pi t / T)) / 2
  w_max(delta) = w_max_base (1 - min(delta, t_c) / t_c)
  paper form:    eps = (1 + w) eps_cond - w eps_uncond
  official form: eps = eps_uncond + w (eps_cond - eps_uncond)

The official cVMDx code also runs the cosine the other way round (w_min at the
noisiest step, w_max at the last): `direction="official"` uses t -> T - t.
`official_step_weights` is the official DDIM loop's own schedule (over the step
index, without delta), for `samplers.official_ddim_sample`.
"""

import jax.numpy as jnp
import numpy as np

from cvmdx_jax.config.sampling import GuidanceConfig
from cvmdx_jax.diffusion import param


def guidance_weight(t, delta, num_steps: int, config: GuidanceConfig = GuidanceConfig()):
  """w(t, delta); t (integer timesteps) and delta broadcast together."""
  t = jnp.asarray(t, jnp.float32)
  if config.direction == "official":
    t = num_steps - t
  w_max = config.w_max_base * (1.0 - jnp.minimum(delta, config.t_c) / config.t_c)
  return config.w_min + (w_max - config.w_min) * (1.0 - jnp.cos(jnp.pi * t / num_steps)) / 2.0


def combine_eps(eps_cond, eps_uncond, w, form: str = "paper"):
  """Combines conditional and unconditional eps; w broadcasts from the left."""
  w = jnp.reshape(w, jnp.shape(w) + (1,) * (jnp.ndim(eps_cond) - jnp.ndim(w)))
  if form == "paper":
    return (1.0 + w) * eps_cond - w * eps_uncond
  return eps_uncond + w * (eps_cond - eps_uncond)


def official_step_weights(num_updates: int, start: float = 0.1, end: float = 1.0) -> np.ndarray:
  """The official DDIM loop's guidance weights, one per update i = 0..n-1 (noisiest
  first): start + (end - start) (1 - cos(pi i / (n - 1))) / 2; the official loop
  does not use delta (its Mahalanobis weighting is commented out).

  Returns:
    (n,) float32; n = 9: 0.1, 0.134, 0.232, 0.378, 0.55, 0.722, 0.868, 0.966, 1.0.
  """
  u = (1.0 - np.cos(np.linspace(0.0, np.pi, num_updates))) / 2.0
  return (start + (end - start) * u).astype(np.float32)


def cond_uncond_v_fn(model_fn, cond, null_cond):
  """`fn(x_t, t) -> (v_cond, v_uncond)`: both branches in one batched model call.

  Args:
    model_fn: (x_t (B, ...), t (B,), cond (B,)) -> v (B, ...).
    cond: (B,) condition tokens.
    null_cond: the unconditional token (scalar).
  """
  cond = jnp.asarray(cond)
  null = jnp.full_like(cond, null_cond)

  def fn(x_t, t):
    v = model_fn(
        jnp.concatenate([x_t, x_t]), jnp.concatenate([t, t]), jnp.concatenate([cond, null])
    )
    return tuple(jnp.split(v, 2))

  return fn


def guided_v_fn(
    model_fn, cond, null_cond, delta, schedule, config: GuidanceConfig = GuidanceConfig()
):
  """Wraps a conditional v-model into a guided `v_fn(x_t, t)` for the samplers.

  Both branches run in one batched call. The eps combination is affine with
  weights summing to 1 and eps = sigma x_t + alpha v is affine in v, so the
  guided v is the same combination of v_cond and v_uncond: returning it is exact
  and avoids dividing by alpha_t -> 0 at t near T.
  Where `config.off` (w = 0 everywhere) only the branch that the combination keeps runs:
  half the evaluations, the same v up to the rounding of a B-row call instead of a 2B-row
  one (~6e-7 on the demo U-Net).

  Args:
    model_fn: (x_t (B, ...), t (B,), cond (B,)) -> v (B, ...).
    cond: (B,) condition tokens.
    null_cond: the unconditional token (scalar).
    delta: (B,) scenario uncertainty (Mahalanobis distance).
    schedule: a `Schedule` (for T).
    config: `GuidanceConfig`.
  """
  if config.off:
    kept = jnp.asarray(cond) if config.form == "paper" else jnp.full_like(cond, null_cond)
    return lambda x_t, t: model_fn(x_t, t, kept)
  branches = cond_uncond_v_fn(model_fn, cond, null_cond)
  num_steps = schedule.num_steps

  def v_fn(x_t, t):
    v_cond, v_uncond = branches(x_t, t)
    w = guidance_weight(t, delta, num_steps, config)
    return combine_eps(v_cond, v_uncond, w, config.form)

  return v_fn


def guided_eps(v_cond, v_uncond, x_t, abar, w, form: str = "paper"):
  """The guided eps exactly as the paper writes it (for tests and analysis)."""
  return combine_eps(
      param.eps_from_v(x_t, v_cond, abar), param.eps_from_v(x_t, v_uncond, abar), w, form
  )
