"""`Observations`: a prediction input holding only what is known at t0 (no futures).

`Scenarios` stays the training and evaluation contract; `from_scenarios` projects one onto
its observed part. Observations built from raw tracks (`from_recording`, `inference.stream`)
also carry where the scenario frame lies in the recording's image frame, so predictions
can be drawn over highD's background image (`to_image`).

Scenario frame (the data contract): x along the ego's direction of travel, y to the
driver's left, origin at the ego's bounding-box centre at t0. Image frame (highD's
tracks.csv): x to the right, y down, metres. drivingDirection 2 drives toward +x: image =
origin + (x, -y); drivingDirection 1 toward -x: image = origin + (-x, y)
(`data.highd`'s road frame, inverted).
"""

import dataclasses

import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.data import frames
from cvmdx_jax.data.scenarios import FIELDS as SCENARIO_FIELDS
from cvmdx_jax.data.scenarios import Scenarios

UNKNOWN_DIRECTION = 0  # direction of a projected `Scenarios` (no image frame)
# field name -> (trailing shape, dtype)
FIELDS = {
    **{
        name: SCENARIO_FIELDS[name]
        for name in ("xi", "mask", "v0", "psi0", "recording_id", "track_id", "frame")
    },
    "origin": ((2,), np.float64),
    "direction": ((), np.int32),
}


@dataclasses.dataclass(frozen=True)
class Observations:
  """M observations at their t0, all fields with leading dimension M.

  Attributes:
    xi: (M, 9, 75, 4) float32 [x, y, v_x, v_y] of ego + 8 neighbours, scenario frame.
    mask: (M, 9, 75) bool, vehicle present at that step.
    v0, psi0: (M,) float32 ego speed (m/s) and heading to the road axis (rad) at t0.
    recording_id, track_id, frame: (M,) int32 provenance (frame = the recording's frame of
      t0); -1 where unknown.
    origin: (M, 2) float64 the ego's bounding-box centre at t0 in the image frame, m
      (NaN where unknown).
    direction: (M,) int32 highD drivingDirection (1 toward -x, 2 toward +x; 0 unknown).
  """

  xi: np.ndarray
  mask: np.ndarray
  v0: np.ndarray
  psi0: np.ndarray
  recording_id: np.ndarray
  track_id: np.ndarray
  frame: np.ndarray
  origin: np.ndarray
  direction: np.ndarray

  def __len__(self) -> int:
    return int(np.shape(self.v0)[0])

  def validate(
      self,
      source: str = "observations",
      fields=tuple(FIELDS),
      *,
      dtypes: bool = True,
      allow_empty: bool = True,
  ) -> "Observations":
    """Checks `fields` (shape (M, ...), dtype unless `dtypes` is False, finite; origin may
    be NaN where direction is 0); raises ValueError naming source and field. The signature
    of `Scenarios.validate`, so a consumer checks either."""
    m = len(self)
    for name in fields:
      shape, dtype = FIELDS[name]
      value = np.asarray(getattr(self, name))
      if value.shape != (m, *shape):
        raise ValueError(
            f"{source}: field '{name}' has shape {value.shape}, " f"expected {(m, *shape)}"
        )
      if dtypes and value.dtype != dtype:
        raise ValueError(
            f"{source}: field '{name}' has dtype {value.dtype}, " f"expected {np.dtype(dtype)}"
        )
      finite = (
          np.isfinite(value).reshape(m, int(np.prod(shape))).all(-1)
          if value.dtype.kind == "f"
          else np.ones(m, bool)
      )
      if name == "origin":
        finite |= np.asarray(self.direction) == UNKNOWN_DIRECTION
      if not np.all(finite):
        raise ValueError(
            f"{source}: field '{name}' holds NaN/inf (observation " f"{int(np.argmin(finite))})"
        )
    if "v0" in fields and np.any(np.asarray(self.v0) < 0):
      raise ValueError(
          f"{source}: field 'v0' is negative (observation "
          f"{int(np.argmax(np.asarray(self.v0) < 0))})"
      )
    if "direction" in fields and not np.isin(self.direction, (0, 1, 2)).all():
      raise ValueError(f"{source}: field 'direction' outside {{0, 1, 2}}")
    if not allow_empty and m == 0:
      raise ValueError(f"{source}: no observations")
    return self


def from_arrays(**arrays) -> Observations:
  """Observations from arrays, each cast to its dtype; missing provenance is -1, a missing
  origin NaN and direction 0 (unknown); validated."""
  m = len(arrays["v0"])
  defaults = {"origin": np.full((m, 2), np.nan), "direction": np.zeros(m)}
  out = {
      name: np.asarray(arrays.get(name, defaults.get(name, np.full(m, -1)))).astype(
          dtype, copy=False
      )
      for name, (_, dtype) in FIELDS.items()
  }
  return Observations(**out).validate()


def from_scenarios(scenarios: Scenarios) -> Observations:
  """The observed part of `scenarios` (futures, controls and labels dropped; no image
  frame: origin NaN, direction 0)."""
  return from_arrays(**{k: v for k, v in scenarios.as_dict().items() if k in FIELDS})


def from_recording(rec, rows) -> Observations:
  """Observations of the ego rows `rows` (N,) of a `data.highd.Recording`, each with 3 s of
  history (`data.frames.observable_rows`, `data.frames.rows_of`), with their image frame."""
  return from_arrays(**frames.observed(rec, rows))


def as_observations(inputs: Scenarios | Observations) -> Observations:
  """`inputs` as Observations (a `Scenarios` projected by `from_scenarios`)."""
  return from_scenarios(inputs) if isinstance(inputs, Scenarios) else inputs


def image_sign(direction) -> np.ndarray:
  """(M,) +1 for drivingDirection 2 (toward +x), -1 for 1."""
  direction = np.asarray(direction)
  if np.any((direction != 1) & (direction != 2)):
    raise ValueError(
        "to_image: an observation without an image frame (direction 0: made "
        "from Scenarios, not from a recording)"
    )
  return np.where(direction == 2, 1.0, -1.0)


def to_image(observations: Observations, xy) -> np.ndarray:
  """Scenario-frame positions (M, ..., 2) of each observation's ego -> the recording's
  image frame (M, ..., 2) float64 (highD's x right, y down; bounding-box centres)."""
  xy = np.asarray(xy, np.float64)
  sign = image_sign(observations.direction).reshape((-1,) + (1,) * (xy.ndim - 1))
  flip = np.concatenate([sign, -sign], -1)
  origin = np.asarray(observations.origin).reshape(
      (len(observations),) + (1,) * (xy.ndim - 2) + (2,)
  )
  return origin + flip * xy


def horizon_s() -> np.ndarray:
  """(125,) seconds after t0 of the predicted steps."""
  return np.arange(1, constants.T_PRED + 1) * constants.DT
