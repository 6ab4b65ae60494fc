"""Vehicle motion model (VMM): controls [a_x, yaw_rate] -> positions.

Per step tau (paper Eq. VMM1-VMM2, with the y-line typo `v` -> `tau` fixed):
  x += v cos(psi) tau + (a cos(psi) - psi_dot v sin(psi)) tau^2 / 2
  y += v sin(psi) tau + (a sin(psi) + psi_dot v cos(psi)) tau^2 / 2
  v += a tau;  psi += psi_dot tau
"""

import jax
import jax.numpy as jnp

from cvmdx_jax import constants


def _step(state, control, dt):
  x, y, v, psi = state
  a, psi_dot = control[..., 0], control[..., 1]
  c, s = jnp.cos(psi), jnp.sin(psi)
  half_dt2 = 0.5 * dt * dt
  x = x + v * c * dt + (a * c - psi_dot * v * s) * half_dt2
  y = y + v * s * dt + (a * s + psi_dot * v * c) * half_dt2
  v = v + a * dt
  psi = psi + psi_dot * dt
  return (x, y, v, psi), jnp.stack([x, y], axis=-1)


def rollout(controls, v0, psi0, dt: float = constants.DT):
  """Integrates controls from the origin.

  Args:
    controls: (..., T, 2) [a_x m/s^2, yaw_rate rad/s].
    v0: (...,) initial speed, m/s.
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
