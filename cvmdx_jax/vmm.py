"""Vehicle motion model (VMM): controls [a_x, yaw_rate] -> positions, and its inverse.

Per step tau (paper Eq. VMM1-VMM2, with the y-line typo `v` -> `tau` fixed):
  x += v cos(psi) tau + (a cos(psi) - psi_dot v sin(psi)) tau^2 / 2
  y += v sin(psi) tau + (a sin(psi) + psi_dot v cos(psi)) tau^2 / 2
  v += a tau;  psi += psi_dot tau
Speed never goes below 0: tau = dt, except in a step where v + a dt < 0, where the vehicle
moves only until it stops, tau = v / -a (so v ends at exactly 0 after the braking distance
v^2 / 2|a|); a standing vehicle under braking stays where it is (tau = 0, heading kept).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants


def _step(state, control, dt):
  x, y, v, psi = state
  a, psi_dot = control[..., 0], control[..., 1]
  stops = v + a * dt < 0  # only with a < 0 (v >= 0)
  tau = jnp.where(stops, jnp.clip(v / jnp.where(stops, -a, 1.0), 0.0, dt), dt)
  c, s = jnp.cos(psi), jnp.sin(psi)
  half_tau2 = 0.5 * tau * tau
  x = x + v * c * tau + (a * c - psi_dot * v * s) * half_tau2
  y = y + v * s * tau + (a * s + psi_dot * v * c) * half_tau2
  v = jnp.where(stops, 0.0, v + a * tau)
  psi = psi + psi_dot * tau
  return (x, y, v, psi), jnp.stack([x, y], axis=-1)


def rollout(controls, v0, psi0, dt: float = constants.DT):
  """Integrates controls from the origin; speed stops at 0 (module docstring).

  Args:
    controls: (..., T, 2) [a_x m/s^2, yaw_rate rad/s].
    v0: (...,) initial speed >= 0, m/s (callers validate; see `Scenarios.validate`).
    psi0: (...,) initial heading, rad.
    dt: step, s.

  Returns:
    (..., T, 2) positions [x, y] in metres after each step, relative to the start.
  """
  controls = jnp.asarray(controls)
  batch = controls.shape[:-2]
  v0 = jnp.broadcast_to(jnp.asarray(v0, controls.dtype), batch)
  psi0 = jnp.broadcast_to(jnp.asarray(psi0, controls.dtype), batch)
  zero = jnp.zeros(batch, controls.dtype)
  steps = jnp.moveaxis(controls, -2, 0)  # (T, ..., 2)
  _, positions = jax.lax.scan(lambda s, c: _step(s, c, dt), (zero, zero, v0, psi0), steps)
  return jnp.moveaxis(positions, 0, -2)


@functools.lru_cache(maxsize=4)
def _fit_matrices(smoothing: float):
  """G = (A^T A + s D^T D)^-1 A^T and H = (A^T A + s D^T D)^-1 s D^T D (numpy, T x T).

  A maps controls to positions of the linearised VMM: x_K = sum_{j<K} dt^2 (K - j - 1/2) a_j.
  """
  t, dt = constants.T_PRED, constants.DT
  k, j = np.meshgrid(np.arange(1, t + 1), np.arange(t), indexing="ij")
  a = np.where(j < k, dt * dt * (k - j - 0.5), 0.0)
  d = np.diff(np.eye(t), axis=0)
  m = a.T @ a + smoothing * d.T @ d
  return (
      np.linalg.solve(m, a.T).astype(np.float32),
      np.linalg.solve(m, smoothing * d.T @ d).astype(np.float32),
  )


@functools.partial(jax.jit, static_argnames=("smoothing", "iterations"))
def fit_controls(future, v0, psi0, smoothing: float = 1e-2, iterations: int = 8):
  """Smooth controls whose `rollout` reproduces `future` (the inverse of the VMM).

  Gauss-Newton on |rollout(u) - future|^2 + smoothing * (|D a|^2 + |D (v_mean w)|^2), with
  the Jacobian of the linearised VMM (x depends on a through A, y on w through v_mean A).
  The residual comes from `rollout` itself, so a future that brakes to a standstill is
  fitted under the same stop-at-zero rule.

  Args:
    future: (M, 125, 2) positions after t0, m.
    v0, psi0: (M,) speed m/s and heading rad at t0.
    smoothing: penalty weight on control differences (larger = smoother, less exact).
    iterations: Gauss-Newton steps.

  Returns:
    (M, 125, 2) [a_x m/s^2, yaw_rate rad/s].
  """
  g, h = (jnp.asarray(x) for x in _fit_matrices(smoothing))
  t = jnp.arange(1, constants.T_PRED + 1) * constants.DT
  dist = jnp.linalg.norm(jnp.diff(future, axis=1, prepend=0 * future[:, :1]), axis=-1)
  v_mean = jnp.maximum(dist.mean(-1) / constants.DT, 1.0)[:, None]  # (M, 1)
  mm = functools.partial(jnp.matmul, precision=constants.EXACT_MATMUL)

  def step(controls, _):
    r = future - rollout(controls, v0, psi0)
    a, w = controls[..., 0], controls[..., 1]
    a = a + mm(r[..., 0], g.T) - mm(a, h.T)
    w = w + mm(r[..., 1] / v_mean, g.T) - mm(w, h.T)
    return jnp.stack([a, w], -1), None

  init = jnp.zeros_like(future)
  init = init.at[..., 0].set(mm(future[:, :, 0] - v0[:, None] * t, g.T))
  init = init.at[..., 1].set(mm(future[:, :, 1] / v_mean - psi0[:, None] * t, g.T))
  controls, _ = jax.lax.scan(step, init, None, length=iterations)
  return controls
