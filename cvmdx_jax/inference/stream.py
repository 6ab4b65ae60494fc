"""Online prediction: one frame of tracked vehicles at a time.

    stream = Stream(predictor, seed=0)
    for frame in frames:   # 25 Hz, consecutive frame numbers
      preds = stream.step(frame, ids, centres, velocities, neighbours=neighbours)
      # preds: `recording.VehiclePredictions` of the vehicles with 3 s of history

A frame gives each vehicle's id, bounding-box centre and velocity in the image frame
(highD's x right, y down; m, m/s), optionally its drivingDirection (else from the sign of
its x velocity: toward +x is 2) and its 8 neighbour ids in `constants.VEHICLE_SLOTS[1:]`
order (highD's precedingId ... rightFollowingId, 0 = none; without them a vehicle is
observed without neighbours). The state keeps the last 75 frames (3 s) per vehicle present
in the last frame: a vehicle missing from a frame is dropped (its history starts again when
it reappears), and a gap in the frame numbers starts every history again. Memory is
O(vehicles x 75).

The observations equal `observations.from_recording` of a recording fed frame by frame (same
road frame, neighbours and masks), and each vehicle draws its noise from (frame, track id)
like `recording.predict`: the predictions equal a whole recording's at the same frames.
"""

import dataclasses

import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.inference import observations as obs_lib
from cvmdx_jax.inference import recording

_SLOTS = constants.NUM_VEHICLES - 1


@dataclasses.dataclass(frozen=True)
class History:
  """The last `constants.T_OBS` frames of V vehicles (numpy), oldest first.

  Attributes:
    frame: the last frame fed (-1 before the first).
    track_id: (V,) int64 ids of the vehicles of that frame.
    pos, vel: (V, 75, 2) float64 centre and velocity in each vehicle's road frame
      (`data.highd`: x along its direction of travel, y to its left).
    valid: (V, 75) bool, the vehicle was present in that frame.
    direction: (V,) int32 drivingDirection (1 or 2).
    neighbours: (V, 8) int64 neighbour ids in the last frame (0 = none).
  """

  frame: int
  track_id: np.ndarray
  pos: np.ndarray
  vel: np.ndarray
  valid: np.ndarray
  direction: np.ndarray
  neighbours: np.ndarray


def empty_history() -> History:
  t = constants.T_OBS
  return History(
      frame=-1,
      track_id=np.zeros(0, np.int64),
      pos=np.zeros((0, t, 2)),
      vel=np.zeros((0, t, 2)),
      valid=np.zeros((0, t), bool),
      direction=np.zeros(0, np.int32),
      neighbours=np.zeros((0, _SLOTS), np.int64),
  )


def update(
    history: History, frame: int, track_id, centre, velocity, direction=None, neighbours=None
) -> History:
  """`history` after frame `frame`: (V,) ids, (V, 2) image-frame centres and velocities,
  optional (V,) drivingDirection and (V, 8) neighbour ids (module docstring)."""
  track_id = np.asarray(track_id, np.int64)
  centre, velocity = np.asarray(centre, np.float64), np.asarray(velocity, np.float64)
  v = len(track_id)
  if centre.shape != (v, 2) or velocity.shape != (v, 2) or len(np.unique(track_id)) != v:
    raise ValueError(
        f"frame {frame}: expected unique ids (V,) and centres / velocities "
        f"(V, 2), got {track_id.shape}, {centre.shape}, {velocity.shape}"
    )
  if direction is None:
    direction = np.where(velocity[:, 0] >= 0, 2, 1)
  direction = np.asarray(direction, np.int32)
  neighbours = (
      np.zeros((v, _SLOTS), np.int64)
      if neighbours is None
      else np.asarray(neighbours, np.int64).reshape(v, _SLOTS)
  )
  if history.frame >= 0 and frame != history.frame + 1:
    history = empty_history()  # a gap: nobody was seen in between
  old = {int(t): i for i, t in enumerate(history.track_id)}
  index = np.array([old.get(int(t), -1) for t in track_id], np.int64)
  seen = index >= 0
  shift = lambda a, new: np.concatenate(
      [
          np.where(seen.reshape((-1,) + (1,) * (a.ndim - 1)), a[np.maximum(index, 0), 1:], 0),
          new[:, None],
      ],
      1,
  )
  sign = np.where(direction == 2, 1.0, -1.0)[:, None]
  flip = np.concatenate([sign, -sign], -1)
  return History(
      frame=int(frame),
      track_id=track_id,
      pos=shift(_or_empty(history.pos, v), centre * flip),
      vel=shift(_or_empty(history.vel, v), velocity * flip),
      valid=shift(_or_empty(history.valid, v), np.ones(v, bool)),
      direction=direction,
      neighbours=neighbours,
  )


def _or_empty(a: np.ndarray, v: int) -> np.ndarray:
  """`a`, or a zero block of V rows when `a` has none (nothing to gather from)."""
  return a if len(a) else np.zeros((max(v, 1), *a.shape[1:]), a.dtype)


def ready(history: History) -> np.ndarray:
  """Indices of the vehicles with 75 frames of history, in increasing track id."""
  full = np.flatnonzero(history.valid.all(-1))
  return full[np.argsort(history.track_id[full], kind="stable")]


def observations(history: History, recording_id: int = 0) -> obs_lib.Observations:
  """Observations at `history.frame` of the `ready` vehicles (as `extract.observed`)."""
  egos = ready(history)
  position = {int(t): i for i, t in enumerate(history.track_id)}
  nbr = np.array(
      [
          [position.get(int(t), -1) if t > 0 else -1 for t in row]
          for row in history.neighbours[egos]
      ],
      np.int64,
  ).reshape(len(egos), _SLOTS)
  rows = np.concatenate([egos[:, None], np.maximum(nbr, 0)], 1)  # (N, 9)
  mask = (
      history.valid[rows] & np.concatenate([np.ones((len(egos), 1), bool), nbr >= 0], 1)[..., None]
  )
  origin = history.pos[egos, -1]
  xy = history.pos[rows] - origin[:, None, None]
  xi = np.concatenate([xy, history.vel[rows]], -1) * mask[..., None]
  vel0 = history.vel[egos, -1]
  sign = np.where(history.direction[egos] == 2, 1.0, -1.0)[:, None]
  return obs_lib.from_arrays(
      xi=xi.astype(np.float32),
      mask=mask,
      v0=np.hypot(vel0[:, 0], vel0[:, 1]).astype(np.float32),
      psi0=np.arctan2(vel0[:, 1], vel0[:, 0]).astype(np.float32),
      recording_id=np.full(len(egos), recording_id),
      track_id=history.track_id[egos],
      frame=np.full(len(egos), history.frame),
      origin=origin * np.concatenate([sign, -sign], -1),
      direction=history.direction[egos],
  )


class Stream:
  """An online predictor: `step` feeds one frame and predicts the vehicles with 3 s of
  history (`recording.predict` with `predictor`, a `Predictor`)."""

  def __init__(self, predictor, seed: int = 0, recording_id: int = 0, samples: bool = False):
    self.predictor, self.seed, self.recording_id, self.samples = (
        predictor,
        seed,
        recording_id,
        samples,
    )
    self.history = empty_history()

  def step(
      self,
      frame: int,
      track_id,
      centre,
      velocity,
      direction=None,
      neighbours=None,
      predict: bool = True,
  ) -> recording.VehiclePredictions | None:
    """Feeds frame `frame` (`update`); returns the predictions of the ready vehicles (None
    when `predict` is False or no vehicle is ready)."""
    self.history = update(self.history, frame, track_id, centre, velocity, direction, neighbours)
    if not predict or len(ready(self.history)) == 0:
      return None
    obs = observations(self.history, self.recording_id)
    return recording.predict(self.predictor, obs, seed=self.seed, samples=self.samples)
