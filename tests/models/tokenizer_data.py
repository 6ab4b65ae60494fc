"""Synthetic scenarios for the tokeniser tests (tests/models, tests/train): three maneuver
classes that differ in the ego's lateral motion, with random speeds and randomly present
neighbours. tests/conftest.py serves `make_scenarios` as the fixture `scenarios_factory`."""

import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.data import from_arrays


def make_scenarios(m: int, seed: int = 0):
  """m class-balanced toy scenarios (label = m-th % 3) in the road-aligned ego frame."""
  rng = np.random.default_rng(seed)
  label = np.arange(m) % constants.NUM_CLASSES
  t = (np.arange(constants.T_OBS) - (constants.T_OBS - 1)) * constants.DT  # -2.96 .. 0 s
  speed = rng.uniform(22.0, 36.0, (m, constants.NUM_VEHICLES, 1))
  lane = np.array([0, 0, 0, 1, 1, 1, -1, -1, -1], np.float32) * 3.5
  gap = np.array([0, -30, 30, 30, 0, -30, 30, 0, -30], np.float32)
  x = gap[None, :, None] + rng.normal(0, 5, (m, 9, 1)) + speed * t
  x[:, 0] = speed[:, 0] * t
  side = np.array([0.0, -1.0, 1.0])[label]  # lcr drifts right (y down), lcl left
  drift = side[:, None] * 1.2 * (1 + t / 3.0) ** 2
  y = np.broadcast_to(lane[None, :, None], (m, 9, constants.T_OBS)).copy()
  y[:, 0] = drift + rng.normal(0, 0.05, (m, constants.T_OBS))
  vx = np.broadcast_to(speed, x.shape)
  vy = np.gradient(y, constants.DT, axis=-1)
  xi = np.stack([x, y, vx, vy], axis=-1).astype(np.float32)
  mask = rng.random((m, 9, 1)) < 0.7
  mask[:, 0] = True
  mask = np.broadcast_to(mask, (m, 9, constants.T_OBS))
  xi = np.where(mask[..., None], xi, 0.0)
  zeros = np.zeros((m, constants.T_PRED, 2), np.float32)
  return from_arrays(
      xi=xi,
      mask=mask,
      future=zeros,
      controls=zeros,
      v0=speed[:, 0, 0],
      psi0=np.zeros(m),
      label=label,
  )
