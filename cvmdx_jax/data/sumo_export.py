"""SUMO FCD output -> the three highD CSV files of one recording.

SUMO gives the front-bumper middle (x, y up) and a navigational angle (degrees, 0 = north,
clockwise). We take the bounding-box centre (front - length/2 along the heading), keep the
visible section [section_start_m, section_start_m + section_length_m], move to image
coordinates (x from the section start, y down from `image_top_m` above the north road edge),
number frames from 1 after the warm-up, derive laneId from the markings (1 + number of
markings above the centre) and recompute all neighbour ids per frame from geometry:
same lane ahead/behind = preceding/following; adjacent lane (left/right in the direction of
travel) longitudinally overlapping = alongside, else the nearest ahead/behind. Values are
rounded to two decimals like highD.
"""

from pathlib import Path

import numpy as np
import pandas as pd

from cvmdx_jax import constants
from cvmdx_jax.data import csv_text, highd, sumo_network
from cvmdx_jax.errors import UserError
from cvmdx_jax.storage import atomic

_KEY_SHIFT = 26  # bits of the centimetre position in the neighbour search key


def _image_markings(cfg, road) -> tuple[np.ndarray, np.ndarray]:
  north, south = sumo_network.lane_markings(road, cfg.median_m)
  top = north[-1] + cfg.image_top_m
  return np.sort(top - north), np.sort(top - south)


def _tracks_from_fcd(fcd: pd.DataFrame, cfg, plan) -> pd.DataFrame:
  """Per-row kinematics in image coordinates, contiguous tracks, ids 1..N, frames from 1."""
  dims = sumo_network.vehicle_dims(plan)
  kind = fcd["type"].map({k: v[0] for k, v in dims.items()}).to_numpy()
  length = fcd["type"].map({k: v[1] for k, v in dims.items()}).to_numpy(np.float64)
  width = fcd["type"].map({k: v[2] for k, v in dims.items()}).to_numpy(np.float64)
  theta = np.deg2rad(fcd["angle"].to_numpy(np.float64))
  hx, hy = np.sin(theta), np.cos(theta)
  cx = fcd["x"].to_numpy(np.float64) - 0.5 * length * hx
  cy = fcd["y"].to_numpy(np.float64) - 0.5 * length * hy
  north, _ = sumo_network.lane_markings(plan.road, cfg.median_m)
  top = north[-1] + cfg.image_top_m
  frame = np.round(fcd["time"].to_numpy() / constants.DT).astype(np.int64)
  frame -= int(round(cfg.warmup_s / constants.DT)) - 1
  speed, acc = fcd["speed"].to_numpy(np.float64), fcd["acc"].to_numpy(np.float64)
  out = pd.DataFrame(
      {
          "frame": frame,
          "sumo_id": fcd["id"].to_numpy(),
          "xc": cx - cfg.section_start_m,
          "yc": top - cy,
          "width": length,
          "height": width,
          "xVelocity": speed * hx,
          "yVelocity": -speed * hy,
          "xAcceleration": acc * hx,
          "yAcceleration": -acc * hy,
          "class": kind,
          "drivingDirection": np.where(hx < 0, 1, 2),
      }
  )
  out = out[(frame >= 1) & (out["xc"] >= 0) & (out["xc"] <= cfg.section_length_m)]
  out = out.sort_values(["sumo_id", "frame"], kind="stable").reset_index(drop=True)
  sid, fr = out["sumo_id"].to_numpy(), out["frame"].to_numpy()
  new_run = np.r_[True, (sid[1:] != sid[:-1]) | (np.diff(fr) != 1)]
  new_vehicle = np.r_[True, sid[1:] != sid[:-1]]
  run = np.cumsum(new_run)
  first_run = np.maximum.accumulate(np.where(new_vehicle, run, 0))
  out = out[run == first_run]  # the first contiguous stretch of each vehicle
  first_frame = out.groupby("sumo_id", sort=False)["frame"].transform("min")
  order = out.assign(f0=first_frame).sort_values(["f0", "sumo_id", "frame"], kind="stable")
  new_id = np.cumsum(
      np.r_[True, order["sumo_id"].to_numpy()[1:] != order["sumo_id"].to_numpy()[:-1]]
  )
  return order.assign(id=new_id).drop(columns=["f0", "sumo_id"]).reset_index(drop=True)


def _neighbours(t: pd.DataFrame) -> dict:
  """Neighbour ids (0 = none) per row, in `highd.NEIGHBOUR_COLUMNS` order, plus the gap."""
  n = len(t)
  sign = np.where(t["drivingDirection"].to_numpy() == 2, 1.0, -1.0)
  s = sign * t["xc"].to_numpy()
  half = 0.5 * t["width"].to_numpy()
  group = t["frame"].to_numpy() * 16 + t["laneId"].to_numpy()
  key = (group << _KEY_SHIFT) + np.round(s * 100).astype(np.int64) + (1 << (_KEY_SHIFT - 1))
  order = np.argsort(key, kind="stable")
  skey, sgroup, ids = key[order], group[order], t["id"].to_numpy()[order]
  s_sorted, half_sorted = s[order], half[order]

  def pick(pos, target_group):
    ok = (pos >= 0) & (pos < n)
    pos = np.clip(pos, 0, n - 1)
    return pos, ok & (sgroup[pos] == target_group)

  def overlaps(pos, ok):
    return ok & (np.abs(s_sorted[pos] - s) < half_sorted[pos] + half)

  rank = np.empty(n, np.int64)
  rank[order] = np.arange(n)
  ahead, ok_a = pick(rank + 1, group)
  behind, ok_b = pick(rank - 1, group)
  out = {
      "precedingId": np.where(ok_a, ids[ahead], 0),
      "followingId": np.where(ok_b, ids[behind], 0),
  }
  gap = np.where(ok_a, s_sorted[ahead] - s - half_sorted[ahead] - half, 0.0)
  left_step = np.where(sign > 0, -1, 1)  # laneId of the left lane = laneId + left_step
  for side, step in (("left", left_step), ("right", -left_step)):
    target = group + step
    idx = np.searchsorted(skey, (target << _KEY_SHIFT) + key - (group << _KEY_SHIFT))
    a1, ok1 = pick(idx, target)  # first at or ahead
    a2, ok2 = pick(idx + 1, target)
    b1, okb1 = pick(idx - 1, target)  # first behind
    b2, okb2 = pick(idx - 2, target)
    ov_a, ov_b = overlaps(a1, ok1), overlaps(b1, okb1)
    closer_a = np.abs(s_sorted[a1] - s) <= np.abs(s_sorted[b1] - s)
    along = np.where(ov_a & (closer_a | ~ov_b), ids[a1], np.where(ov_b, ids[b1], 0))
    pre = np.where(ov_a, np.where(ok2 & ~overlaps(a2, ok2), ids[a2], 0), np.where(ok1, ids[a1], 0))
    fol = np.where(
        ov_b, np.where(okb2 & ~overlaps(b2, okb2), ids[b2], 0), np.where(okb1, ids[b1], 0)
    )
    out[f"{side}PrecedingId"], out[f"{side}AlongsideId"], out[f"{side}FollowingId"] = (
        pre,
        along,
        fol,
    )
  out["gap"] = gap
  out["ahead_row"] = np.where(ok_a, order[ahead], -1)
  return out


def _write_csv(frame: pd.DataFrame, path: Path) -> None:
  with atomic.writing(path, "w") as f:
    f.write(csv_text.table_csv(frame))  # pandas' float_format="%.2f" text, 3.5x faster


def export_recording(fcd: pd.DataFrame, cfg, plan, out_dir: Path) -> int:
  """Writes XX_tracks.csv, XX_tracksMeta.csv, XX_recordingMeta.csv; returns the row count.

  Args:
    fcd: SUMO FCD rows with columns time, id, x, y, angle, type, speed, acc.
    cfg: the `sumo` config section (section, image and time settings).
    plan: the recording's `sumo_plan.RecordingPlan` (XX = plan.recording_id, its road and
      vehicle types).
    out_dir: destination directory.
  """
  if 2 * plan.road.lanes + 3 >= 16:
    raise UserError(f"sumo export: {plan.road.lanes} lanes per direction, at most 6")
  upper, lower = _image_markings(cfg, plan.road)
  t = _track_rows(fcd, cfg, plan, np.sort(np.r_[upper, lower]))
  tracks = t[list(highd.TRACKS_COLUMNS)]
  meta = _tracks_meta(t)
  rec_meta = _recording_meta(plan, meta, upper, lower)
  out_dir.mkdir(parents=True, exist_ok=True)
  paths = highd.recording_paths(out_dir, plan.recording_id)
  _write_csv(tracks, paths["tracks"])
  _write_csv(meta[list(highd.TRACKS_META_COLUMNS)], paths["tracksMeta"])
  _write_csv(rec_meta[list(highd.RECORDING_META_COLUMNS)], paths["recordingMeta"])
  return len(tracks)


def _track_rows(fcd: pd.DataFrame, cfg, plan, markings: np.ndarray) -> pd.DataFrame:
  """The rows of XX_tracks.csv (and the columns tracksMeta is computed from), rounded to
  0.01; `markings` the image y of every lane marking, ascending."""
  t = _tracks_from_fcd(fcd, cfg, plan)
  t["x"] = (t["xc"] - 0.5 * t["width"]).round(2)
  t["y"] = (t["yc"] - 0.5 * t["height"]).round(2)
  # laneId of the centre as written (rounded), so readers recompute the same lane.
  t["laneId"] = 1 + np.searchsorted(markings, (t["y"] + 0.5 * t["height"]).to_numpy())
  nb = _neighbours(t)
  forward = np.where(t["drivingDirection"] == 2, cfg.section_length_m - t["xc"], t["xc"])
  t["frontSightDistance"] = forward
  t["backSightDistance"] = cfg.section_length_m - forward
  has = nb["ahead_row"] >= 0
  speed = np.abs(t["xVelocity"].to_numpy())
  pre_vx = np.where(has, t["xVelocity"].to_numpy()[nb["ahead_row"]], 0.0)
  closing = speed - np.abs(pre_vx)
  t["dhw"] = np.where(has, nb["gap"], 0.0)
  t["thw"] = np.where(has & (speed > 0.1), nb["gap"] / np.maximum(speed, 0.1), 0.0)
  t["ttc"] = np.where(
      has & (np.abs(closing) > 1e-3),
      nb["gap"] / np.where(np.abs(closing) > 1e-3, closing, 1.0),
      0.0,
  )
  t["precedingXVelocity"] = pre_vx
  for column in highd.NEIGHBOUR_COLUMNS:
    t[column] = nb[column]
  return t.round(2)


def _tracks_meta(t: pd.DataFrame) -> pd.DataFrame:
  """One XX_tracksMeta.csv row per track of the rows `t`."""
  g = t.groupby("id", sort=True)
  abs_vx = t["xVelocity"].abs().groupby(t["id"])
  positive = lambda col: t[col].where(t[col] > 0).groupby(t["id"]).min().fillna(-1)
  return pd.DataFrame(
      {
          "id": g["id"].first(),
          "width": g["width"].first(),
          "height": g["height"].first(),
          "initialFrame": g["frame"].min(),
          "finalFrame": g["frame"].max(),
          "numFrames": g["frame"].count(),
          "class": g["class"].first(),
          "drivingDirection": g["drivingDirection"].first(),
          "traveledDistance": (g["x"].last() - g["x"].first()).abs(),
          "minXVelocity": abs_vx.min(),
          "maxXVelocity": abs_vx.max(),
          "meanXVelocity": abs_vx.mean(),
          "minDHW": positive("dhw"),
          "minTHW": positive("thw"),
          "minTTC": positive("ttc"),
          "numLaneChanges": g["laneId"].agg(lambda x: int(np.count_nonzero(np.diff(x.to_numpy())))),
      }
  ).round(2)


def _recording_meta(plan, meta: pd.DataFrame, upper, lower) -> pd.DataFrame:
  """The one XX_recordingMeta.csv row of `plan`'s recording with tracks `meta` and the
  lane markings `upper`, `lower` (image y, m)."""
  num_frames = int(round(plan.duration_s * constants.FRAME_RATE_HZ))
  fmt = lambda values: ";".join(f"{v:.2f}" for v in values)
  return pd.DataFrame(
      [
          {
              "id": plan.recording_id,
              "frameRate": constants.FRAME_RATE_HZ,
              "locationId": 0,
              "speedLimit": round(plan.road.speed_limit_ms, 2),
              "month": "01.2000",
              "weekDay": "Mon",
              "startTime": "00:00",
              "duration": num_frames * constants.DT,
              "totalDrivenDistance": meta["traveledDistance"].sum(),
              "totalDrivenTime": meta["numFrames"].sum() * constants.DT,
              "numVehicles": len(meta),
              "numCars": int((meta["class"] == "Car").sum()),
              "numTrucks": int((meta["class"] == "Truck").sum()),
              "upperLaneMarkings": fmt(upper),
              "lowerLaneMarkings": fmt(lower),
          }
      ]
  )
