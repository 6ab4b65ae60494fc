"""`Scenarios`: the one data contract every reader produces and every model reads.

Frame: road-aligned and right-handed, x along the road in the ego's direction of
travel, y to the driver's left, origin at the ego's position at the last observed
step t0. Units: metres, seconds, m/s, m/s^2, rad.
"""

import dataclasses

import jax
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.errors import UserError

# field name -> (trailing shape, dtype)
FIELDS = {
    "xi": ((constants.NUM_VEHICLES, constants.T_OBS, constants.NUM_FEATURES), np.float32),
    "mask": ((constants.NUM_VEHICLES, constants.T_OBS), np.bool_),
    "future": ((constants.T_PRED, 2), np.float32),
    "controls": ((constants.T_PRED, 2), np.float32),
    "v0": ((), np.float32),
    "psi0": ((), np.float32),
    "label": ((), np.int32),
    "time_to_lane_change": ((), np.float32),
    "recording_id": ((), np.int32),
    "track_id": ((), np.int32),
    "frame": ((), np.int32),
}


def _leading(value) -> int | None:
  """The leading dimension of an array-like `value`; None for a scalar or a ragged list."""
  try:
    shape = np.shape(value)
  except ValueError:
    return None
  return shape[0] if shape else None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scenarios:
  """M scenarios as arrays (numpy or JAX), all with leading dimension M.

  Attributes:
    xi: (M, 9, 75, 4) [x, y, v_x, v_y] of ego + 8 neighbours (slot order
      `constants.VEHICLE_SLOTS`), 0 where `mask` is False.
    mask: (M, 9, 75) True where the vehicle exists at that step.
    future: (M, 125, 2) ego positions after t0 (steps t0+1 .. t0+125).
    controls: (M, 125, 2) [a_x m/s^2, yaw_rate rad/s]; `vmm.rollout(controls,
      v0, psi0)` reproduces `future`.
    v0: (M,) ego speed at t0, m/s, >= 0.
    psi0: (M,) ego heading at t0 relative to the road axis, rad.
    label: (M,) 0 keep lane, 1 lane change right, 2 lane change left.
    time_to_lane_change: (M,) s from t0 to the lane crossing; -1 for keep lane
      or where unknown.
    recording_id, track_id, frame: (M,) provenance (frame = highD frame of t0);
      -1 where unknown.
  """

  xi: np.ndarray
  mask: np.ndarray
  future: np.ndarray
  controls: np.ndarray
  v0: np.ndarray
  psi0: np.ndarray
  label: np.ndarray
  time_to_lane_change: np.ndarray
  recording_id: np.ndarray
  track_id: np.ndarray
  frame: np.ndarray

  def __len__(self) -> int:
    """M: the leading dimension most fields share (ties: the first in `FIELDS` order),
    so that one field of another length is the one `validate` blames."""
    counts = [n for n in map(_leading, self.as_dict().values()) if n is not None]
    return int(max(counts, key=counts.count)) if counts else 0

  def take(self, index) -> "Scenarios":
    """The scenarios at `index` (an int array, slice or boolean mask)."""
    return Scenarios(**{k: np.asarray(v)[index] for k, v in self.as_dict().items()})

  def as_dict(self) -> dict:
    return {name: getattr(self, name) for name in FIELDS}

  def validate(
      self,
      source: str = "scenarios",
      fields=tuple(FIELDS),
      *,
      dtypes: bool = True,
      allow_empty: bool = True,
  ) -> "Scenarios":
    """Checks `fields` against the contract; raises ValueError naming source and field.

    Args:
      source: where the scenarios come from (file, split), for the message.
      fields: names of the fields to check: shape (M, ...), dtype, finiteness, label
        range. Default: all, as every reader must produce them; a consumer names
        the fields it reads (the predictor: xi, mask, v0, psi0).
      dtypes: False accepts any dtype (for a consumer that casts what it reads).
      allow_empty: False refuses M = 0.

    Returns:
      self.
    """
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
      raise UserError(f"Scenarios.validate: unknown field(s) {unknown}")
    m = len(self)
    for name, (shape, dtype) in FIELDS.items():
      if name not in fields:
        continue
      try:
        value = np.asarray(getattr(self, name))
      except (ValueError, TypeError) as e:  # ragged lists, ...
        raise UserError(f"{source}: field '{name}' is not an array ({e})") from None
      if value.dtype.kind not in "biuf":  # text, objects, complex: no real numbers
        raise UserError(
            f"{source}: field '{name}' has dtype {value.dtype}, expected " "real numbers"
        )
      if value.shape != (m, *shape):
        raise UserError(
            f"{source}: field '{name}' has shape {value.shape}, " f"expected {(m, *shape)}"
        )
      if dtypes and value.dtype != dtype:
        raise UserError(
            f"{source}: field '{name}' has dtype {value.dtype}, " f"expected {np.dtype(dtype)}"
        )
      if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
        bad = int(np.argwhere(~np.isfinite(value).reshape(m, -1).all(-1))[0, 0])
        raise UserError(f"{source}: field '{name}' holds NaN/inf (scenario {bad})")
    v0 = np.asarray(self.v0) if "v0" in fields else None  # a list given as a field
    if v0 is not None and np.any(v0 < 0):
      bad = int(np.argmax(v0 < 0))
      raise UserError(f"{source}: field 'v0' is negative ({v0[bad]} m/s, scenario {bad})")
    label = np.asarray(self.label) if "label" in fields else None
    if label is not None and np.any((label < 0) | (label >= constants.NUM_CLASSES)):
      raise UserError(f"{source}: field 'label' outside 0..{constants.NUM_CLASSES - 1}")
    if not allow_empty and m == 0:
      raise UserError(f"{source}: no scenarios")
    return self


def balanced_indices(labels, seed: int, size: int | None = None) -> np.ndarray:
  """Sorted indices of a class-balanced selection, each class drawn without replacement.

  Args:
    labels: (M,) class labels 0 .. NUM_CLASSES - 1.
    seed: numpy seed of the draw.
    size: None undersamples every class to the smallest class count (the dataset
      builder); an int takes ceil(size / NUM_CLASSES) of each class (all of a smaller
      one) and keeps the first `size` indices (evaluation subsets).

  Returns:
    (K,) int64 indices in increasing order.
  """
  rng = np.random.default_rng(seed)
  groups = [np.flatnonzero(np.asarray(labels) == c) for c in range(constants.NUM_CLASSES)]
  n = min(len(g) for g in groups) if size is None else -(-size // constants.NUM_CLASSES)
  index = np.sort(np.concatenate([rng.choice(g, min(n, len(g)), replace=False) for g in groups]))
  return index if size is None else index[:size]


def from_arrays(**arrays) -> Scenarios:
  """Builds `Scenarios` casting each field to its contract dtype; missing
  provenance fields (time_to_lane_change, recording_id, track_id, frame) are -1."""
  m = len(arrays["label"])
  out = {}
  for name, (_, dtype) in FIELDS.items():
    value = arrays.get(name)
    out[name] = (
        np.full((m,), -1, dtype) if value is None else np.asarray(value).astype(dtype, copy=False)
    )
  return Scenarios(**out).validate()


def concatenate(parts) -> Scenarios:
  """Concatenates a sequence of `Scenarios` along M."""
  parts = list(parts)
  if not parts:
    raise ValueError("concatenate: empty sequence of Scenarios")
  return Scenarios(**{name: np.concatenate([getattr(p, name) for p in parts]) for name in FIELDS})
