"""Normalisation of the observed scenario xi for the scenario tokeniser.

Per feature, xi_n = (xi - offset) / scale, and 0 wherever the vehicle is absent:

| feature | offset | scale   | why                                                         |
|---------|--------|---------|-------------------------------------------------------------|
| x       | 0      | 100 m   | as cVMD; the ego covers ~90 m in 3 s, neighbours lie within |
|         |        |         | ~+-100 m of the ego at t0, so x_n is mostly in [-2, 1]      |
| y       | 0      | 3.5 m   | as cVMD: one lane width per unit                            |
| v_x     | 30 m/s | 2 m/s   | our v_x is the absolute speed (~20-40 m/s on a highway);    |
|         |        |         | a 2 m/s unit makes a 1 m/s speed change over the 3 s (the   |
|         |        |         | acceleration trend that predicts the future) worth 0.25 in  |
|         |        |         | squared error; cVMD's v_x / 30 would hide it                |
| v_y     | 0      | 0.1 m/s | as cVMD: the lateral drift that announces a lane change     |
|         |        |         | (0.2-1.5 m/s) is 2-15 units                                 |

The scales decide what the tokens capture: the reconstruction error is their only
unsupervised signal, and with coarse velocity units (10 m/s, 0.5 m/s) it was dominated by
the neighbours' positions, so tokens barely told an accelerating or drifting ego from a
steady one (measured in docs/log, "Tokens that predict the future").

The mask itself is fed to the encoder as a fifth channel (`encoder_input`), so an absent
vehicle is not mistaken for one at (0, 0) driving at 30 m/s.
"""

import jax
import jax.numpy as jnp
import numpy as np

XI_OFFSET = np.array([0.0, 0.0, 30.0, 0.0], np.float32)  # x m, y m, v_x m/s, v_y m/s
XI_SCALE = np.array([100.0, 3.5, 2.0, 0.1], np.float32)


def normalize_xi(xi: jax.typing.ArrayLike, mask: jax.typing.ArrayLike) -> jax.Array:
  """Physical xi -> normalised xi, zero where absent.

  Args:
    xi: (..., 9, 75, 4) [x m, y m, v_x m/s, v_y m/s].
    mask: (..., 9, 75) bool, True where the vehicle exists.

  Returns:
    (..., 9, 75, 4) float32.
  """
  xi_n = (jnp.asarray(xi, jnp.float32) - XI_OFFSET) / XI_SCALE
  return jnp.where(jnp.asarray(mask)[..., None], xi_n, 0.0)


def denormalize_xi(xi_n: jax.typing.ArrayLike) -> jax.Array:
  """Normalised (..., 4) features -> physical [m, m, m/s, m/s]."""
  return jnp.asarray(xi_n) * XI_SCALE + XI_OFFSET


def encoder_input(xi: jax.typing.ArrayLike, mask: jax.typing.ArrayLike) -> jax.Array:
  """(..., 9, 75, 4) xi + (..., 9, 75) mask -> (..., 9, 75, 5): normalised xi and mask."""
  mask_f = jnp.asarray(mask, jnp.float32)[..., None]
  return jnp.concatenate([normalize_xi(xi, mask), mask_f], axis=-1)
