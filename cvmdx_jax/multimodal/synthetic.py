"""Sets of sampled highway futures around a known number of modes (numpy).

`mode_sets` draws highway-like sets of sampled futures around 1, 2 or 3 well-separated
modes (keep lane, lane change left/right by one 3.5 m lane, keep speed or brake): inputs
with a known answer for checks and benchmarks of the hypotheses stage
(`experiments/benchmark_sampling.py`, tests/multimodal). Not on the prediction path.
"""

import numpy as np

from cvmdx_jax import constants

LANE_WIDTH = 3.5  # m
# (lateral offset in lanes, braking or not) of each mode kind.
MODE_KINDS = ((0, 0), (1, 0), (-1, 0), (0, 1), (1, 1), (-1, 1))


def mode_sets(
    seed: int,
    num_sets: int,
    num_samples: int = 9,
    num_modes=None,
    brake: float = -4.0,
    num_steps: int = constants.T_PRED,
    dt: float = constants.DT,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Sets of sampled highway futures around a known number of modes.

  Each set has a speed v0 ~ U(22, 38) m/s and 1-3 distinct mode kinds
  (`MODE_KINDS`: lane offset -1/0/+1 lanes by a smooth 3-4.5 s lane change
  starting within 0.3-1.5 s, acceleration 0 or `brake`), each holding at
  least 2 of the samples. Per sample: speed noise 0.5 m/s, acceleration noise
  0.15 m/s^2, lateral offset noise 0.15 m, lane-change timing jitter 0.15 s,
  and 0.03 m white position noise.

  Args:
    seed: numpy seed.
    num_sets: B.
    num_samples: N per set (>= 2 per mode).
    num_modes: int or (B,) ints in 1..3; default uniform over 1..3.
    brake: acceleration of braking modes, m/s^2.
    num_steps: T.
    dt: step, s.

  Returns:
    trajectories: (B, N, T, 2) float32 positions [x, y] in metres after each step.
    num_modes: (B,) int true number of modes.
    mode_ids: (B, N) int mode index (0..num_modes-1) of each sample.
  """
  rng = np.random.default_rng(seed)
  if num_modes is None:
    num_modes = rng.integers(1, 4, size=num_sets)
  num_modes = np.broadcast_to(np.asarray(num_modes, int), (num_sets,))
  if np.any(num_modes < 1) or np.any(num_modes > 3) or 2 * num_modes.max() > num_samples:
    raise ValueError(
        f"mode_sets: num_modes must be in 1..3 with 2 samples each, got "
        f"{np.unique(num_modes)} for num_samples={num_samples}"
    )
  t = dt * np.arange(1, num_steps + 1)
  trajectories = np.empty((num_sets, num_samples, num_steps, 2))
  mode_ids = np.empty((num_sets, num_samples), int)
  for b, k in enumerate(num_modes):
    kinds = rng.choice(len(MODE_KINDS), size=k, replace=False)
    extra = rng.multinomial(num_samples - 2 * k, np.full(k, 1.0 / k))
    ids = np.repeat(np.arange(k), 2 + extra)
    lanes, brakes = np.array([MODE_KINDS[i] for i in kinds]).T
    start = rng.uniform(0.3, 1.5, k)[ids] + rng.normal(0, 0.15, num_samples)
    duration = rng.uniform(3.0, 4.5, k)[ids] + rng.normal(0, 0.15, num_samples)
    u = np.clip((t[None] - start[:, None]) / duration[:, None], 0.0, 1.0)
    smooth = u**3 * (10 - 15 * u + 6 * u**2)
    speed = rng.uniform(22, 38) + rng.normal(0, 0.5, num_samples)
    accel = brake * brakes[ids] + rng.normal(0, 0.15, num_samples)
    x = speed[:, None] * t + 0.5 * accel[:, None] * t**2
    y = LANE_WIDTH * lanes[ids][:, None] * smooth + rng.normal(0, 0.15, (num_samples, 1))
    noise = rng.normal(0, 0.03, (num_samples, num_steps, 2))
    trajectories[b] = np.stack([x, y], axis=-1) + noise
    mode_ids[b] = ids
  return trajectories.astype(np.float32), num_modes.copy(), mode_ids
