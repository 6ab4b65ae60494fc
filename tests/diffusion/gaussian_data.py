"""Gaussian data x0 ~ N(MU, diag(STD^2)) and its exact v-predictor (closed form)."""

import jax.numpy as jnp
import numpy as np

MU = np.array([0.5, -0.3], np.float32)
STD = np.array([0.2, 0.6], np.float32)


def gaussian_v(x_t, t, abar_table):
  """E[v | x_t] for x0 ~ N(MU, diag(STD^2)): the exact denoiser of this data."""
  abar = abar_table[t][:, None, None]
  alpha, sigma = jnp.sqrt(abar), jnp.sqrt(1.0 - abar)
  var = alpha**2 * STD**2 + sigma**2
  centred = x_t - alpha * MU
  e_x0 = MU + alpha * STD**2 / var * centred
  e_eps = sigma / var * centred
  return alpha * e_eps - sigma * e_x0
