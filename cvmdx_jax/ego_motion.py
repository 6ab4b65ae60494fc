"""Ego-motion features of a scenario, and the controls they extrapolate (beyond the paper).

`ego_features(xi, mask) -> (M, F)` reads only the observed window xi (M, 9, 75, 4)
[x, y, v_x, v_y] (scenario frame: x along the road, y to the left, origin at the ego at
t0, 25 Hz; ego = vehicle 0). Each feature is (value - centre) / scale, clipped to [-CLIP, CLIP]:

| # | feature | unit | centre | scale |
|---|---|---|---|---|
| 0 | speed at t0, \\|v\\| | m/s | 30 | 10 |
| 1 | longitudinal acceleration: least-squares slope of \\|v\\|, last 1 s | m/s^2 | 0 | 1 |
| 2 | mean acceleration: \\|v\\| change since the first observed step / its age | m/s^2 | 0 | 1 |
| 3 | yaw rate: least-squares slope of heading atan2(v_y, v_x), last 1 s | rad/s | 0 | 0.02 |
| 4 | heading at t0 relative to the road axis | rad | 0 | 0.03 |
| 5 | lateral velocity v_y at t0 | m/s | 0 | 1 |
| 6 | lateral displacement over the last 1 s, y(t0) - y(t0 - 1 s) | m | 0 | 1 |
| 7 | lateral displacement since the first observed step (t0 - 2.96 s) | m | 0 | 2 |
| 8 | lateral offset from the lane centre, proxy (below; 0 without reference) | m | 0 | 1 |
| 9 | 1 where feature 8 has a same-lane neighbour, else 0 | - | 0 | 1 |
| 10 | 1 where a preceding vehicle is there at t0, else 0 | - | 0 | 1 |
| 11 | gap to the preceding vehicle at t0, min(x, 150 m) (150 m when none) | m | 50 | 50 |
| 12 | its closing speed v_x,preceding - v_x at t0 (0 when none) | m/s | 0 | 5 |
| 13 + 4k | 1 where neighbour k of `NEIGHBOURS` is there at t0, else 0 | - | 0 | 1 |
| 14 + 4k | its longitudinal offset x_k - x at t0, clipped to +-150 m (absent: +150 | m | 0 | 50 |
|         | ahead, -150 behind, 0 alongside) | | | |
| 15 + 4k | its relative speed v_x,k - v_x at t0 (0 when absent) | m/s | 0 | 5 |
| 16 + 4k | its lateral offset y_k - y at t0 (0 when absent) | m | 0 | 3.75 |

xi holds no lane markings and its origin is the ego, not the lane, so the true offset from
the lane centre is not derivable from xi alone; feature 8 is the ego's y minus the mean y
of the same-lane neighbours at t0 (slots "preceding" and "following", assigned by lane).
Features 6-7 give the lateral position history relative to t0. Features 13-40 describe
the other seven neighbours at t0 (k = 0 .. 6 over `NEIGHBOURS`): whether the adjacent lanes
exist and have room, and whether they are faster, is what a lane change depends on.

`residual_controls(ego, decay_s)` turns features 1 and 3 back into the ego's current
[a_x, yaw rate] and extrapolates them over the 125 predicted steps with an exponential
decay: the base that the `ego_residual` conditionings subtract from their targets.

Conditionings of the denoiser (`diffusion.conditioning`): "token" (the paper: token q
only), "ego_film" (the features' MLP embedding is added to the time + token FiLM
embedding), "ego_residual" (token only, but the target is controls minus
`residual_controls`), "ego_film_residual" (both). Guidance keeps the paper's meaning:
the unconditional branch drops the token only; both branches see the same features.
"""

import jax
import jax.numpy as jnp

from cvmdx_jax import constants
from cvmdx_jax.errors import UserError

# name -> (centre, scale) of the normalised features, in the order of the table above
FEATURES = (
    ("speed", 30.0, 10.0),
    ("accel_1s", 0.0, 1.0),
    ("accel_window", 0.0, 1.0),
    ("yaw_rate_1s", 0.0, 0.02),
    ("heading", 0.0, 0.03),
    ("lateral_velocity", 0.0, 1.0),
    ("lateral_shift_1s", 0.0, 1.0),
    ("lateral_shift_window", 0.0, 2.0),
    ("lane_offset", 0.0, 1.0),
    ("lane_reference", 0.0, 1.0),
    ("leader", 0.0, 1.0),
    ("leader_gap", 50.0, 50.0),
    ("leader_closing_speed", 0.0, 5.0),
)
# the neighbours of features 13-40 and where an absent one is put (+1 ahead, -1 behind)
NEIGHBOURS = (
    ("following", -1.0),
    ("leftPreceding", 1.0),
    ("leftAlongside", 0.0),
    ("leftFollowing", -1.0),
    ("rightPreceding", 1.0),
    ("rightAlongside", 0.0),
    ("rightFollowing", -1.0),
)
FEATURES += tuple(
    feature
    for slot, _ in NEIGHBOURS
    for feature in (
        (f"{slot}_present", 0.0, 1.0),
        (f"{slot}_dx", 0.0, 50.0),
        (f"{slot}_dv", 0.0, 5.0),
        (f"{slot}_dy", 0.0, 3.75),
    )
)
NUM_FEATURES = len(FEATURES)
CONDITIONINGS = ("token", "ego_film", "ego_residual", "ego_film_residual")
CLIP = 5.0  # normalised features are clipped to [-CLIP, CLIP]
RECENT_STEPS = constants.FRAME_RATE_HZ + 1  # samples spanning the last second
MAX_GAP_M = 150.0
_ACCEL, _YAW_RATE = 1, 3
_FOLLOWING, _PRECEDING = (constants.VEHICLE_SLOTS.index(s) for s in ("following", "preceding"))
_NEIGHBOUR_SLOTS = tuple(constants.VEHICLE_SLOTS.index(slot) for slot, _ in NEIGHBOURS)
_ABSENT_DX = tuple(MAX_GAP_M * side for _, side in NEIGHBOURS)  # m, where one is absent


def _slope(values, weights):
  """Weighted least-squares slope per second of (..., n) samples dt apart (exact for
  lines); 0 where fewer than two samples have weight."""
  t = constants.DT * jnp.arange(values.shape[-1], dtype=values.dtype)
  total = jnp.maximum(jnp.sum(weights, -1, keepdims=True), 1.0)
  centred = t - jnp.sum(weights * t, -1, keepdims=True) / total
  mean = jnp.sum(weights * values, -1, keepdims=True) / total
  num = jnp.sum(weights * centred * (values - mean), -1)
  den = jnp.sum(weights * centred**2, -1)
  return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 0.0)


@jax.jit  # one compiled call over a split, not ~100 dispatches of its operations
def ego_features(xi, mask):
  """Normalised ego-motion features (table in the module docstring).

  Steps where the ego is masked (histories shorter than 3 s in cvMD `.mat` data) are
  left out: slopes use the observed steps, window features start at the first one.

  Args:
    xi: (M, 9, 75, 4) observed [x, y, v_x, v_y] (m, m/s), scenario frame.
    mask: (M, 9, 75) True where a vehicle exists; the ego exists at t0.

  Returns:
    (M, NUM_FEATURES) float32.
  """
  xi = jnp.asarray(xi, jnp.float32)
  mask = jnp.asarray(mask, bool)
  ego, seen = xi[:, 0], mask[:, 0]
  speed = jnp.linalg.norm(ego[..., 2:4], axis=-1)
  heading = jnp.unwrap(jnp.arctan2(ego[..., 3], ego[..., 2]), axis=-1)
  recent = slice(-RECENT_STEPS, None)
  weights = seen[:, recent].astype(jnp.float32)
  first = jnp.argmax(seen, axis=-1)  # first observed step
  at = lambda series, step: jnp.take_along_axis(series, step[:, None], axis=-1)[:, 0]
  window_s = (constants.T_OBS - 1 - first) * constants.DT
  start_1s = jnp.maximum(first, constants.T_OBS - RECENT_STEPS)
  lane_present = mask[:, (_PRECEDING, _FOLLOWING), -1]
  lane_y = jnp.sum(jnp.where(lane_present, xi[:, (_PRECEDING, _FOLLOWING), -1, 1], 0.0), -1)
  has_lane = jnp.any(lane_present, axis=-1)
  lane_offset = jnp.where(
      has_lane, ego[:, -1, 1] - lane_y / jnp.maximum(jnp.sum(lane_present, -1), 1), 0.0
  )
  leader = mask[:, _PRECEDING, -1]
  lead = xi[:, _PRECEDING, -1]
  present = mask[:, _NEIGHBOUR_SLOTS, -1]  # (M, 7)
  other = xi[:, _NEIGHBOUR_SLOTS, -1]  # (M, 7, 4)
  neighbours = jnp.stack(
      [
          present.astype(jnp.float32),
          jnp.where(
              present,
              jnp.clip(other[..., 0] - ego[:, -1:, 0], -MAX_GAP_M, MAX_GAP_M),
              jnp.asarray(_ABSENT_DX, jnp.float32),
          ),
          jnp.where(present, other[..., 2] - ego[:, -1:, 2], 0.0),
          jnp.where(present, other[..., 1] - ego[:, -1:, 1], 0.0),
      ],
      axis=-1,
  ).reshape(xi.shape[0], -1)
  raw = jnp.stack(
      [
          speed[:, -1],
          _slope(speed[:, recent], weights),
          jnp.where(
              window_s > 0, (speed[:, -1] - at(speed, first)) / jnp.maximum(window_s, 1e-3), 0.0
          ),
          _slope(heading[:, recent], weights),
          heading[:, -1],
          ego[:, -1, 3],
          ego[:, -1, 1] - at(ego[..., 1], start_1s),
          ego[:, -1, 1] - at(ego[..., 1], first),
          lane_offset,
          has_lane.astype(jnp.float32),
          leader.astype(jnp.float32),
          jnp.where(leader, jnp.clip(lead[:, 0] - ego[:, -1, 0], 0.0, MAX_GAP_M), MAX_GAP_M),
          jnp.where(leader, lead[:, 2] - ego[:, -1, 2], 0.0),
      ],
      axis=-1,
  )
  raw = jnp.concatenate([raw, neighbours], axis=-1)
  centre = jnp.asarray([c for _, c, _ in FEATURES], jnp.float32)
  scale = jnp.asarray([s for _, _, s in FEATURES], jnp.float32)
  return jnp.clip((raw - centre) / scale, -CLIP, CLIP)


def check_conditioning(conditioning: str) -> str:
  """Returns `conditioning`; ValueError naming diffusion.conditioning if unknown."""
  if conditioning not in CONDITIONINGS:
    raise UserError(
        f"diffusion.conditioning must be one of {CONDITIONINGS}, " f"got {conditioning!r}"
    )
  return conditioning


def uses_film(conditioning: str) -> bool:
  """True where the denoiser receives the features as a conditioning vector."""
  return check_conditioning(conditioning) in ("ego_film", "ego_film_residual")


def uses_residual(conditioning: str) -> bool:
  """True where the denoiser's target is the residual to `residual_controls`."""
  return check_conditioning(conditioning) in ("ego_residual", "ego_film_residual")


def residual_controls(ego, decay_s):
  """The ego's current [a_x, yaw rate], decayed over the prediction horizon.

  Args:
    ego: (..., NUM_FEATURES) features from `ego_features`.
    decay_s: (tau_a, tau_r) time constants of the decay exp(-t / tau) of a_x and of
      the yaw rate, s; inf holds a control constant.

  Returns:
    (..., 125, 2) [a_x m/s^2, yaw rate rad/s] of the predicted steps, the control of
    step k (from t0 + k dt to t0 + (k + 1) dt) decayed by exp(-k dt / tau).
  """
  ego = jnp.asarray(ego, jnp.float32)
  current = jnp.stack(
      [ego[..., _ACCEL] * FEATURES[_ACCEL][2], ego[..., _YAW_RATE] * FEATURES[_YAW_RATE][2]],
      axis=-1,
  )
  t = constants.DT * jnp.arange(constants.T_PRED, dtype=jnp.float32)
  decay = jnp.exp(-t[:, None] / jnp.asarray(decay_s, jnp.float32))
  return current[..., None, :] * decay
