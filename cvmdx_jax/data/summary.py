"""Dataset summary: counts, lane changes per recording, kinematics, VMM reconstruction error."""

import jax
import numpy as np

from cvmdx_jax import constants, vmm

_rollout = jax.jit(vmm.rollout)


def _range(x) -> dict:
  x = np.asarray(x, np.float64)
  return {
      "min": round(float(x.min()), 3),
      "max": round(float(x.max()), 3),
      "mean": round(float(x.mean()), 3),
  }


def summarize_split(s) -> dict:
  """Summary of one split's `Scenarios` (JSON-able)."""
  label = np.asarray(s.label)
  lc = label > 0
  # A lane change = (recording, track, crossing frame); count distinct ones per recording.
  crossing = np.asarray(s.frame) + np.round(
      np.asarray(s.time_to_lane_change) * constants.FRAME_RATE_HZ
  ).astype(np.int64)
  events = np.unique(
      np.stack([np.asarray(s.recording_id), np.asarray(s.track_id), crossing], -1)[lc], axis=0
  )
  rec, per_rec = np.unique(events[:, 0], return_counts=True) if len(events) else ([], [])
  pred = np.asarray(_rollout(s.controls, s.v0, s.psi0))
  err = np.linalg.norm(pred - np.asarray(s.future), axis=-1)
  ade, fde = err.mean(-1), err[:, -1]
  controls = np.asarray(s.controls)
  return {
      "count": int(len(label)),
      "per_class": {name: int(np.sum(label == c)) for c, name in enumerate(constants.CLASS_NAMES)},
      "lane_changes_per_recording": {str(int(r)): int(n) for r, n in zip(rec, per_rec)},
      "speed_v0_ms": _range(s.v0),
      "accel_ms2": _range(controls[..., 0]),
      "yaw_rate_rads": _range(controls[..., 1]),
      "reconstruction_m": {
          "ade_mean": round(float(ade.mean()), 4),
          "ade_p95": round(float(np.percentile(ade, 95)), 4),
          "ade_max": round(float(ade.max()), 4),
          "fde_mean": round(float(fde.mean()), 4),
      },
      "beyond_caps": {
          "accel_gt_4": round(float(np.mean(np.abs(controls[..., 0]) > constants.ACCEL_SCALE)), 5),
          "yaw_rate_gt_0.7": round(
              float(np.mean(np.abs(controls[..., 1]) > constants.YAW_RATE_SCALE)), 5
          ),
      },
  }


def summarize(splits: dict) -> dict:
  """{split name: summarize_split(scenarios)}."""
  return {name: summarize_split(s) for name, s in splits.items()}
