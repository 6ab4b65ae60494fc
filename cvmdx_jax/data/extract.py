"""Scenario extraction from validated highD-format recordings.

Rules (all in `ExtractionConfig`):
- Reference frame t0 = the last observed step; the ego needs 75 rows up to t0 and 125 after it
  within its own track.
- Label from the first laneId change of the ego in (t0, t0 + 5 s]: none = 0 kl; else left or
  right in the ego's direction of travel (laneId grows to the left for drivingDirection 1 and
  to the right for 2): 1 lcr, 2 lcl. `time_to_lane_change` = (crossing frame - t0) / 25 Hz,
  the crossing frame being the first with the new laneId; -1 for kl.
- Lane-change windows: t0 = crossing frame - offset for each of `lc_offsets_s`.
  Keep-lane windows: t0 every `kl_stride_s` along each track, where no laneId change follows.
- Neighbours: the 8 ids of the ego's row at t0 (0 = absent), their centre positions and
  velocities over the 75 observed frames, masked where they have no row.
- Coordinates: road frame of the ego's direction, origin at the ego's centre at t0.
- Balancing: each class randomly undersampled to the smallest class count (seeded).
- Controls [a_x, yaw_rate]: `vmm.fit_controls`, a smoothed least-squares fit through `vmm.rollout`.
"""

import dataclasses

import numpy as np

from cvmdx_jax import constants, sharding, vmm
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.errors import UserError

_OBS_OFFSETS = np.arange(-(constants.T_OBS - 1), 1)  # rows t0-74 .. t0
_FUTURE_OFFSETS = np.arange(1, constants.T_PRED + 1)  # rows t0+1 .. t0+125


@dataclasses.dataclass(frozen=True)
class ExtractionConfig:
  """Extraction settings (documented in the module docstring)."""

  lc_offsets_s: tuple = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5)  # s before crossing
  kl_stride_s: float = 1.0  # s between keep-lane windows of one track
  balance: bool = True  # undersample every class to the smallest one
  seed: int = 0  # balancing draw
  control_smoothing: float = 1e-2  # weight of the control-difference penalty in the fit
  control_iterations: int = 8  # Gauss-Newton steps of the control fit


def default_config() -> ExtractionConfig:
  return ExtractionConfig()


def as_config(config) -> ExtractionConfig:
  """ExtractionConfig from None, a mapping or a ConfigDict (unknown keys -> ValueError)."""
  if config is None or isinstance(config, ExtractionConfig):
    return config or ExtractionConfig()
  values = dict(config.to_dict() if hasattr(config, "to_dict") else config)
  names = {f.name for f in dataclasses.fields(ExtractionConfig)}
  unknown = sorted(set(values) - names)
  if unknown:
    raise UserError(f"extraction config: unknown keys {unknown}")
  values["lc_offsets_s"] = tuple(values.get("lc_offsets_s", ExtractionConfig.lc_offsets_s))
  return ExtractionConfig(**values)


def candidates(rec, config: ExtractionConfig) -> dict:
  """Reference rows t0 with labels: {'row', 'label', 'ttlc'} (N,) arrays."""
  ids, lane = rec.track_id, rec.lane
  same_track = np.r_[False, ids[1:] == ids[:-1]]
  crossing = np.flatnonzero(same_track & (np.r_[0, np.diff(lane)] != 0))
  steps = np.round(np.asarray(config.lc_offsets_s) * constants.FRAME_RATE_HZ).astype(np.int64)
  lc_rows = (crossing[:, None] - steps[None, :]).ravel()
  stride = max(1, int(round(config.kl_stride_s * constants.FRAME_RATE_HZ)))
  within = np.arange(len(ids)) - rec.first_row[ids]
  kl_rows = np.flatnonzero(within % stride == 0)
  rows = np.unique(np.r_[lc_rows, kl_rows])
  rows = rows[(rows >= 0) & (rows < len(ids))]
  start, count = rec.first_row[ids[rows]], rec.num_frames[ids[rows]]
  rows = rows[(rows - start >= constants.T_OBS - 1) & (rows + constants.T_PRED < start + count)]

  nxt = np.searchsorted(crossing, rows, side="right")
  has = nxt < len(crossing)
  # Without any lane change (crossing empty) every row is keep-lane; index 1 is a dummy.
  cross = np.where(has, np.r_[crossing, 1][np.minimum(nxt, len(crossing))], 1)
  has &= (cross - rows <= constants.T_PRED) & (ids[cross] == ids[rows])
  step = np.sign(lane[cross] - lane[cross - 1]) * np.where(rec.direction[rows] == 1, 1, -1)
  label = np.where(has, np.where(step > 0, 2, 1), 0)
  keep = np.where(has, np.isin(rows, lc_rows), np.isin(rows, kl_rows))
  ttlc = np.where(has, (cross - rows) / constants.FRAME_RATE_HZ, -1.0)
  return {"row": rows[keep], "label": label[keep].astype(np.int32), "ttlc": ttlc[keep]}


def windows(rec, rows: np.ndarray) -> dict:
  """Observation windows, futures and start states of the ego rows `rows` (N,)."""
  future = rec.pos[rows[:, None] + _FUTURE_OFFSETS] - rec.pos[rows][:, None]
  return {**observed(rec, rows), "future": future.astype(np.float32)}


def observed(rec, rows: np.ndarray) -> dict:
  """What is known at t0 of the ego rows `rows` (N,), each with 74 rows of its track before
  it: xi, mask, v0, psi0 and the provenance track_id, frame, recording_id."""
  ego_obs = rows[:, None] + _OBS_OFFSETS  # (N, 75)
  origin = rec.pos[rows]  # (N, 2)
  nid = rec.neighbours[rows]  # (N, 8)
  frames = rec.frame[rows][:, None, None] + _OBS_OFFSETS  # (N, 1, 75)
  rel = frames - rec.first_frame[nid][..., None]  # (N, 8, 75)
  valid = (nid[..., None] > 0) & (rel >= 0) & (rel < rec.num_frames[nid][..., None])
  nbr_rows = np.where(valid, rec.first_row[nid][..., None] + rel, 0)
  all_rows = np.concatenate([ego_obs[:, None], nbr_rows], 1)  # (N, 9, 75)
  mask = np.concatenate([np.ones_like(valid[:, :1]), valid], 1)
  xy = rec.pos[all_rows] - origin[:, None, None]
  xi = np.concatenate([xy, rec.vel[all_rows]], -1) * mask[..., None]
  vel0 = rec.vel[rows]
  return {
      "xi": xi.astype(np.float32),
      "mask": mask,
      "v0": np.hypot(vel0[:, 0], vel0[:, 1]).astype(np.float32),
      "psi0": np.arctan2(vel0[:, 1], vel0[:, 0]).astype(np.float32),
      "track_id": rec.track_id[rows],
      "frame": rec.frame[rows],
      "recording_id": np.full(len(rows), rec.recording_id),
  }


def _fit_in_chunks(future, v0, psi0, config: ExtractionConfig, chunk: int = 2048):
  """`vmm.fit_controls` over fixed-size chunks (one compilation, bounded memory)."""
  out = []
  for start in range(0, len(future), chunk):
    n = min(chunk, len(future) - start)
    pad = lambda x: sharding.pad_batch(x[start : start + n], chunk)[0]
    out.append(
        np.asarray(
            vmm.fit_controls(
                pad(future), pad(v0), pad(psi0), config.control_smoothing, config.control_iterations
            )
        )[:n]
    )
  return np.concatenate(out) if out else np.zeros((0, constants.T_PRED, 2), np.float32)


def scenarios_from_recordings(recordings, config, source: str) -> scenarios_lib.Scenarios:
  """Extracts, balances and fits controls over an iterable of `Recording`s.

  Keep-lane windows are thinned per recording to the larger lane-change count before the
  final balancing, so memory stays proportional to the lane-change count.
  """
  config = as_config(config)
  parts, labels, ttlc = [], [], []
  for index, rec in enumerate(recordings):
    cand = candidates(rec, config)
    keep = np.arange(len(cand["row"]))
    if config.balance:
      rng = np.random.default_rng([config.seed, index])
      kl = np.flatnonzero(cand["label"] == 0)
      n_lc = max(np.sum(cand["label"] == 1), np.sum(cand["label"] == 2))
      kl = rng.choice(kl, min(len(kl), n_lc), replace=False)
      keep = np.sort(np.r_[kl, np.flatnonzero(cand["label"] > 0)]).astype(np.int64)
    parts.append(windows(rec, cand["row"][keep]))
    labels.append(cand["label"][keep])
    ttlc.append(cand["ttlc"][keep])
  if not parts or sum(len(x) for x in labels) == 0:
    raise DataError(
        source,
        "empty selection: no scenario satisfies the extraction rules",
        column="recording_ids",
    )
  arrays = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
  arrays["label"] = np.concatenate(labels)
  arrays["time_to_lane_change"] = np.concatenate(ttlc)
  if config.balance:
    index = scenarios_lib.balanced_indices(arrays["label"], config.seed)
    if len(index) == 0:
      raise DataError(
          source, "empty selection: a class has no scenario, cannot balance", column="label"
      )
    arrays = {k: v[index] for k, v in arrays.items()}
  arrays["controls"] = _fit_in_chunks(arrays["future"], arrays["v0"], arrays["psi0"], config)
  return scenarios_lib.from_arrays(**arrays)
