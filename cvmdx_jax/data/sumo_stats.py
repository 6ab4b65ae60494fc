"""Statistics of highD-format recordings that show how the SUMO recordings differ.

Per recording (`recording_stats`): vehicles, truck share, per-vehicle mean speed percentiles
of cars and trucks (km/h, |meanXVelocity| of tracksMeta), lane changes per vehicle, and the
lane-change duration: for each laneId change of a track, the length of the run of frames
around the crossing in which the lateral speed |vy| exceeds `lat_speed_ms` (s). With the
recording's `plans.json` entry (`sumo.PLANS_FILE`), `plan_columns` adds its road and traffic.
"""

import json
from pathlib import Path

import numpy as np
import pandas as pd

from cvmdx_jax import constants
from cvmdx_jax.data import highd, sumo
from cvmdx_jax.data.errors import DataError


def lane_change_durations(rec: highd.Recording, lat_speed_ms: float = 0.1) -> np.ndarray:
  """(E,) duration in s of each lane change of `rec` (E = laneId changes whose crossing row
  moves laterally faster than `lat_speed_ms`)."""
  same_track = np.r_[False, rec.track_id[1:] == rec.track_id[:-1]]
  crossing = same_track & np.r_[False, rec.lane[1:] != rec.lane[:-1]]
  moving = np.abs(rec.vel[:, 1]) > lat_speed_ms
  run_start = moving & ~(same_track & np.r_[False, moving[:-1]])
  run = np.cumsum(run_start)
  length = np.bincount(run[moving], minlength=int(run.max(initial=0)) + 1)
  rows = np.flatnonzero(crossing & moving)
  return length[run[rows]] / constants.FRAME_RATE_HZ


def _percentiles(values, qs=(10, 50, 90)) -> list:
  values = np.asarray(values, np.float64)
  return [round(float(np.percentile(values, q)), 1) for q in qs] if len(values) else []


def recording_stats(data_dir, recording_id: int) -> dict:
  """Statistics of one recording (JSON-able); see the module docstring."""
  paths = highd.recording_paths(data_dir, recording_id)
  meta = pd.read_csv(paths["tracksMeta"])
  kmh = meta["meanXVelocity"].abs().to_numpy() * 3.6
  trucks = (meta["class"] == "Truck").to_numpy()
  durations = lane_change_durations(highd.read_recording(data_dir, recording_id))
  return {
      "vehicles": int(len(meta)),
      "truck_share": round(float(trucks.mean()), 3),
      "car_kmh_p10_50_90": _percentiles(kmh[~trucks]),
      "truck_kmh_p10_50_90": _percentiles(kmh[trucks]),
      "lane_changes_per_vehicle": round(float(meta["numLaneChanges"].mean()), 3),
      "lane_change_s_p10_50_90": _percentiles(durations),
      "lane_changes_timed": int(len(durations)),
  }


def plan_columns(plan: dict) -> dict:
  """The road and traffic of a `plans.json` entry, in the units of the config."""
  road = plan["road"]
  return {
      "split": plan["split"],
      "lanes": road["lanes"],
      "lane_width_m": road["lane_width_m"],
      "speed_limit_kmh": round(road["speed_limit_ms"] * 3.6),
      "flow_per_lane": round(plan["flow_per_lane"]),
      "truck_share_set": round(plan["truck_share"], 2),
      "car_following": plan["car_following"],
  }


def sumo_table(rec_dir) -> list:
  """One row per recording of a SUMO `recordings` directory: plan columns + statistics."""
  rec_dir = Path(rec_dir)
  try:
    plans = json.loads((rec_dir / sumo.PLANS_FILE).read_text())
  except ValueError as e:
    raise DataError(rec_dir / sumo.PLANS_FILE, f"not valid JSON ({e})") from e
  return [
      {"recording": int(rid), **plan_columns(plan), **recording_stats(rec_dir, int(rid))}
      for rid, plan in sorted(plans.items(), key=lambda kv: int(kv[0]))
  ]
