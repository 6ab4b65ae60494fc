"""Conversions between the v, eps and x0 parameterisations.

With alpha_t = sqrt(abar_t) and sigma_t = sqrt(1 - abar_t):
  x_t = alpha_t x0 + sigma_t eps,   v = alpha_t eps - sigma_t x0,
  x0 = alpha_t x_t - sigma_t v,     eps = sigma_t x_t + alpha_t v.
`abar` broadcasts against the arrays from the left: pass abar of shape (B,) for
arrays (B, ...).
"""

import jax.numpy as jnp


def _coefs(abar, like):
  abar = jnp.reshape(abar, jnp.shape(abar) + (1,) * (jnp.ndim(like) - jnp.ndim(abar)))
  return jnp.sqrt(abar), jnp.sqrt(1.0 - abar)


def q_sample(x0, eps, abar):
  """x_t = alpha x0 + sigma eps."""
  alpha, sigma = _coefs(abar, x0)
  return alpha * x0 + sigma * eps


def v_from_x0_eps(x0, eps, abar):
  """v = alpha eps - sigma x0 (the training target)."""
  alpha, sigma = _coefs(abar, x0)
  return alpha * eps - sigma * x0


def x0_from_v(x_t, v, abar):
  alpha, sigma = _coefs(abar, x_t)
  return alpha * x_t - sigma * v


def eps_from_v(x_t, v, abar):
  alpha, sigma = _coefs(abar, x_t)
  return sigma * x_t + alpha * v


def v_from_eps(x_t, eps, abar):
  """Inverse of `eps_from_v`; unstable where alpha -> 0 (t near T)."""
  alpha, sigma = _coefs(abar, x_t)
  return (eps - sigma * x_t) / alpha


def eps_from_x0(x_t, x0, abar):
  """eps = (x_t - alpha x0) / sigma."""
  alpha, sigma = _coefs(abar, x_t)
  return (x_t - alpha * x0) / sigma
