"""Per-recording SUMO settings: the road, the traffic and the drivers of every recording.

Recordings are numbered 1, 2, ... in split order (`cfg.recordings`: how many train, val, test,
test_ood, val_ood). Each gets a `RecordingPlan` drawn with
`np.random.default_rng([cfg.seed, id])` from the ranges of the `sumo` config section
(documented in `configs/dataset.py`):
- road and duration: lanes per direction cycle through `cfg.lanes` within each split (so a
  split of two or more recordings has both lane counts), lane width `cfg.lane_width_m`, speed
  limit one of `cfg.speed_limits_kmh`, `cfg.duration_s`;
  test_ood recordings take the held-out road `cfg.held_out` instead (lanes, lane width, speed
  limit and flow per lane that no other recording has) and its recorded duration, val_ood
  recordings a second held-out road `cfg.val_held_out` (for choosing settings on a road no
  train recording has without reading test_ood);
- traffic: flow per lane and carriageway, truck share, car-following model;
- drivers: `cfg.car_types` car and `cfg.truck_types` truck vTypes. For each parameter with
  range (lo, hi) the recording draws a centre u ~ U(0, 1) per class, and each type a value at
  clip(u + U(-s, s), 0, 1) of the range (s = `cfg.type_spread`; log scale for the
  lane-change eagerness parameters), so recordings differ in their drivers' behaviour and the
  types of one recording differ around it.
"""

import dataclasses
import json

import numpy as np

from cvmdx_jax.errors import UserError
from cvmdx_jax.storage import atomic

SPLITS = ("train", "val", "test", "test_ood", "val_ood")  # val_ood last: adding it renumbers none
HELD_OUT_ROADS = {"test_ood": "held_out", "val_ood": "val_held_out"}  # split -> cfg section
CAR_FOLLOWING = ("Krauss", "IDM")
_LOG_SCALE = ("lc_speed_gain", "lc_keep_right")  # ratios: drawn uniformly in log space


@dataclasses.dataclass(frozen=True)
class Road:
  """One road: lanes per direction, lane width (m), speed limit (m/s)."""

  lanes: int
  lane_width_m: float
  speed_limit_ms: float


@dataclasses.dataclass(frozen=True)
class DriverType:
  """One SUMO vType: size, desired speed, car following and lane changing (SI units)."""

  name: str  # vType id
  vclass: str  # highD class: Car | Truck
  probability: float  # share of the flow
  length_m: float
  width_m: float
  speed_factor: float  # mean desired speed / speed limit (per vehicle: normal, sd speed_dev)
  speed_dev: float
  desired_max_speed_ms: float  # cap on the desired speed (times the vehicle's speed factor)
  accel: float  # m/s^2
  decel: float  # comfortable deceleration, m/s^2
  sigma: float  # driver imperfection (Krauss; IDM ignores it)
  tau: float  # desired time headway, s
  lc_speed_gain: float  # eagerness to change lanes for speed
  lc_keep_right: float  # eagerness to return to the right
  max_speed_lat: float  # lateral speed, m/s (sets the lane-change duration)
  lc_accel_lat: float  # lateral acceleration, m/s^2


@dataclasses.dataclass(frozen=True)
class RecordingPlan:
  """Everything SUMO needs to simulate one recording."""

  recording_id: int
  split: str
  duration_s: float  # recorded time
  road: Road
  flow_per_lane: float  # veh/h per lane and carriageway
  truck_share: float
  car_following: str  # Krauss | IDM
  types: tuple  # DriverType, cars first

  @property
  def flow_veh_per_hour(self) -> float:
    """Poisson arrivals per carriageway, veh/h."""
    return self.flow_per_lane * self.road.lanes

  def to_json(self) -> dict:
    return dataclasses.asdict(self)


def split_ids(cfg) -> dict:
  """{split: [recording ids]}, numbered 1.. in `SPLITS` order from `cfg.recordings`."""
  out, start = {}, 1
  for name in SPLITS:
    count = int(cfg.recordings.get(name, 0))
    out[name] = list(range(start, start + count))
    start += count
  return out


def _uniform(rng, bounds, log: bool = False, u=None) -> float:
  lo, hi = (float(b) for b in bounds)
  u = rng.uniform() if u is None else u
  if log:
    return float(np.exp(np.log(lo) + u * (np.log(hi) - np.log(lo))))
  return lo + u * (hi - lo)


def _types(rng, ranges, vclass: str, count: int, share: float, spread: float) -> list:
  ranges = ranges.to_dict() if hasattr(ranges, "to_dict") else dict(ranges)
  centre = {key: rng.uniform() for key in sorted(ranges)}
  out = []
  for k in range(count):
    values = {}
    for key in sorted(ranges):
      u = float(np.clip(centre[key] + rng.uniform(-spread, spread), 0.0, 1.0))
      values[key] = _uniform(rng, ranges[key], key in _LOG_SCALE, u)
    cap = values.pop("desired_max_speed_kmh", None)
    try:
      out.append(
          DriverType(
              name=f"{vclass.lower()}{k}",
              vclass=vclass,
              probability=share / count,
              desired_max_speed_ms=cap / 3.6 if cap else 0.0,
              **values,
          )
      )
    except TypeError as err:
      raise UserError(f"sumo.{vclass.lower()}: {err} (expected the DriverType fields)") from err
  return out


def draw(cfg, recording_id: int, split: str, index: int) -> RecordingPlan:
  """The plan of recording `recording_id`, the `index`-th recording of `split`."""
  rng = np.random.default_rng([cfg.seed, recording_id])
  if split in HELD_OUT_ROADS:
    h = cfg[HELD_OUT_ROADS[split]]
    road = Road(int(h.lanes), float(h.lane_width_m), float(h.speed_limit_kmh) / 3.6)
    flow = _uniform(rng, h.flow_per_lane)
    duration = float(h.duration_s)
  else:
    lanes = tuple(cfg.lanes)
    limit = float(cfg.speed_limits_kmh[rng.integers(len(cfg.speed_limits_kmh))])
    road = Road(int(lanes[index % len(lanes)]), float(cfg.lane_width_m), limit / 3.6)
    flow = _uniform(rng, cfg.flow_per_lane)
    duration = float(cfg.duration_s)
  truck_share = _uniform(rng, cfg.truck_share)
  car_following = str(cfg.car_following[rng.integers(len(cfg.car_following))])
  if car_following not in CAR_FOLLOWING:
    raise UserError(f"sumo.car_following: '{car_following}' is not one of {CAR_FOLLOWING}")
  types = _types(rng, cfg.car, "Car", cfg.car_types, 1.0 - truck_share, cfg.type_spread) + _types(
      rng, cfg.truck, "Truck", cfg.truck_types, truck_share, cfg.type_spread
  )
  return RecordingPlan(
      recording_id, split, duration, road, flow, truck_share, car_following, tuple(types)
  )


def plans(cfg) -> dict:
  """{recording id: RecordingPlan} of every recording of `cfg` (the `sumo` section)."""
  return {
      rid: draw(cfg, rid, split, index)
      for split, ids in split_ids(cfg).items()
      for index, rid in enumerate(ids)
  }


def write_plans(plan_by_id: dict, path) -> None:
  """Writes the plans as JSON (a record of what each recording simulates)."""
  atomic.write_text(
      path, json.dumps({str(k): p.to_json() for k, p in plan_by_id.items()}, indent=1) + "\n"
  )
