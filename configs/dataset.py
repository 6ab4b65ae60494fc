"""Dataset settings for experiments/make_dataset.py.

Run: `.venv/bin/python experiments/make_dataset.py --config=configs/dataset.py
--data_dir=data/sumo` (presets after the path: `:small` for the demo, `:tiny` for tests;
other sources with `--config.source=highd --config.highd_dir=/path/to/highD/data` or
`--config.source=cvmd_mat --config.mat_dir=/path/with/train_and_test`).

Splits, all by recording (a recording's scenarios are in one split only):
- sumo: train / val / test on roads and traffic drawn from the ranges below, test_ood on
  a held-out road (`sumo.held_out`: 4 lanes per direction of 3.5 m, 110 km/h, a denser flow
  per lane) that no other recording has, and val_ood on a second held-out road
  (`sumo.val_held_out`: 3 lanes of 3.5 m, 90 km/h) to choose settings for roads never seen
  without reading test_ood. Recordings are numbered in that order (`sumo.recordings`); each
  one's road, traffic and drivers are in `<data_dir>/recordings/plans.json`
  (`cvmdx_jax.data.sumo_plan`). A split of 0 recordings is not built:
  `--config.sumo.recordings.train=0` (and val, test, val_ood) with
  `--config.sumo.held_out.lanes=2 ...` makes a test_ood-only dataset of a road of your
  own, for a trained model (docs/usage.md).
- highd: `splits` (recording ids): test = ids ending in 3, 6 or 9 (18 of 60), val = ids
  ending in 0 (6 of 60), train = the other 36; test_ood and val_ood empty (not built)
  unless given. A split given no ids is not built: `--config.splits.train=()
  --config.splits.val=() --config.splits.test=(1,2)` makes a test-only dataset of a road
  never seen, for a trained model (docs/usage.md).
- cvmd_mat: `mat_dir/train` and `mat_dir/test`; val = `mat_val_fraction` of each class's
  train files, drawn with `seed`.

Default SUMO data: 10 train, 2 val and 3 test recordings of 240 s, 2 test_ood recordings
of 100 s and 1 val_ood recording of 120 s (>= 9,000 train scenarios; sizes and build times
in BUILD_NOTES.md). Ranges, one draw per recording, chosen to cover highD-like behaviour
(car speeds mostly 80-130 km/h, trucks 80-90 km/h, 10-30 % trucks, lane changes over ~4-6 s):
3 or 2 lanes of 3.75 m, speed limit 100, 120 or 130 km/h, 500-1000 veh/h per lane, Krauss or
IDM car following; driver ranges in `sumo.car` / `sumo.truck` (SUMO vType parameters, SI
units).
`:small` (the demo): 12 / 2 / 2 recordings of 120 s, 1 test_ood of 40 s and 1 val_ood of
60 s (two val recordings, so that val holds both lane counts).
"""

import ml_collections

from configs import common

# highD split by recording (fixed): test = ids ending in 3, 6 or 9, val = ids ending in 0.
HIGHD_TEST = tuple(i for i in range(1, 61) if i % 10 in (3, 6, 9))
HIGHD_VAL = tuple(i for i in range(1, 61) if i % 10 == 0)
HIGHD_TRAIN = tuple(i for i in range(1, 61) if i not in HIGHD_TEST + HIGHD_VAL)


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  """arg: '' (default), 'small' or 'tiny'."""
  arg = common.parse_arg(arg, small=False, tiny=False)
  c = ml_collections.ConfigDict()
  c.source = "sumo"  # sumo | highd | cvmd_mat
  c.seed = 0  # draw of the cvmd_mat val files
  c.highd_dir = ""  # directory with XX_tracks.csv etc. (source=highd)
  c.mat_dir = ""  # directory with train/ and test/ class folders (source=cvmd_mat)
  c.mat_val_fraction = 0.15  # share of each class's train files moved to val (cvmd_mat)
  # Recording ids per split (source=highd); a split given no ids is not built.
  c.splits = ml_collections.ConfigDict()
  c.splits.train = HIGHD_TRAIN
  c.splits.val = HIGHD_VAL
  c.splits.test = HIGHD_TEST
  c.splits.test_ood = ()
  c.splits.val_ood = ()

  c.extraction = _extraction()
  c.sumo = _sumo()
  if arg.small:
    _small(c.sumo)
  if arg.tiny:
    _tiny(c)
  return c


def _extraction() -> ml_collections.ConfigDict:
  """Scenario extraction from tracks (`cvmdx_jax.data.extract`)."""
  e = ml_collections.ConfigDict()
  e.lc_offsets_s = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5)  # s before crossing
  e.kl_stride_s = 1.0  # s between keep-lane windows of one track
  e.balance = True  # undersample each class to the smallest one
  e.seed = 0  # balancing draw
  e.control_smoothing = 1e-2  # control-difference penalty of the controls fit
  e.control_iterations = 8  # Gauss-Newton steps of the controls fit
  return e


def _sumo() -> ml_collections.ConfigDict:
  """The SUMO recordings: splits, geometry, road and traffic ranges, drivers, held-out roads."""
  s = ml_collections.ConfigDict()
  s.seed = 0  # SUMO seed = seed * 1000 + recording id; plan draws seeded by (seed, id)
  s.recordings = ml_collections.ConfigDict(  # recordings per split, numbered 1.. in this order
      {"train": 10, "val": 2, "test": 3, "test_ood": 2, "val_ood": 1}
  )
  s.workers = 2  # SUMO processes at once
  s.warmup_s = 60.0  # simulated before frame 1
  s.duration_s = 240.0  # recorded time per recording
  # Geometry shared by every road.
  s.median_m = 2.0  # gap between the carriageways
  s.road_length_m = 1400.0  # simulated road
  s.section_start_m = 250.0  # visible ("recorded") section start
  s.section_length_m = 1000.0  # visible section (highD sees ~420 m)
  s.image_top_m = 8.0  # image y of the northern road edge
  s.lateral_resolution = 0.8  # sublane width, m
  # Road and traffic of the train / val / test recordings.
  s.lanes = (3, 2)  # lanes per direction, cycled over each split's recordings
  s.lane_width_m = 3.75
  s.speed_limits_kmh = (100.0, 120.0, 130.0)  # one drawn per recording
  s.flow_per_lane = (500.0, 1000.0)  # veh/h per lane and carriageway, uniform
  s.truck_share = (0.1, 0.3)  # share of trucks in the flow, uniform
  s.car_following = ("Krauss", "IDM")  # one drawn per recording
  # Drivers: per recording a centre in each (low, high) range, per vType centre +- spread.
  s.car_types = 3  # car vTypes per recording
  s.truck_types = 2  # truck vTypes per recording
  s.type_spread = 0.3  # fraction of each range a vType may lie from the recording's centre
  s.car = _car()
  s.truck = _truck()
  # The held-out road of the test_ood recordings (drivers drawn as above).
  s.held_out = ml_collections.ConfigDict(
      {
          "lanes": 4,
          "lane_width_m": 3.5,
          "speed_limit_kmh": 110.0,
          "flow_per_lane": (700.0, 900.0),
          "duration_s": 100.0,
      }
  )
  # The held-out road of the val_ood recordings: lane width and speed limit of no other
  # recording, 3 lanes so that both lane-change directions are there.
  s.val_held_out = ml_collections.ConfigDict(
      {
          "lanes": 3,
          "lane_width_m": 3.5,
          "speed_limit_kmh": 90.0,
          "flow_per_lane": (800.0, 1000.0),
          "duration_s": 120.0,
      }
  )
  return s


def _car() -> ml_collections.ConfigDict:
  """The ranges of a recording's car drivers (SUMO vType parameters, SI units)."""
  return ml_collections.ConfigDict(
      {
          "length_m": (4.2, 5.0),
          "width_m": (1.75, 2.0),
          "speed_factor": (0.95, 1.15),  # mean desired speed / speed limit
          "speed_dev": (0.08, 0.15),  # per-vehicle spread of the speed factor
          "accel": (1.5, 3.0),
          "decel": (3.5, 5.0),
          "sigma": (0.1, 0.5),
          "tau": (0.9, 1.5),
          "lc_speed_gain": (1.0, 6.0),
          "lc_keep_right": (0.5, 3.0),  # log-uniform
          "max_speed_lat": (0.7, 1.3),
          "lc_accel_lat": (0.6, 1.2),
      }
  )


def _truck() -> ml_collections.ConfigDict:
  """The ranges of a recording's truck drivers (SUMO vType parameters, SI units)."""
  return ml_collections.ConfigDict(
      {
          "length_m": (12.0, 18.0),
          "width_m": (2.45, 2.55),
          "speed_factor": (1.0, 1.0),
          "speed_dev": (0.03, 0.05),
          "desired_max_speed_kmh": (80.0, 92.0),  # trucks keep to their own cap
          "accel": (0.6, 1.2),
          "decel": (3.0, 4.0),
          "sigma": (0.05, 0.3),
          "tau": (1.2, 2.0),
          "lc_speed_gain": (0.2, 1.5),
          "lc_keep_right": (1.0, 4.0),
          "max_speed_lat": (0.4, 0.8),
          "lc_accel_lat": (0.3, 0.7),
      }
  )


def _small(s: ml_collections.ConfigDict) -> None:
  """`:small` (the demo) on the sumo section `s`."""
  # 12 train recordings (6 until 2026-11-23): with the demo's steps unchanged (30 epochs
  # instead of 60), val mean-of-9 ADE 0.87 against 0.90 over three seeds (BUILD_NOTES.md,
  # "Twice the roads")
  s.recordings = ml_collections.ConfigDict(
      {"train": 12, "val": 2, "test": 2, "test_ood": 1, "val_ood": 1}
  )
  s.duration_s = 120.0
  s.held_out.duration_s = 40.0
  s.val_held_out.duration_s = 60.0


def _tiny(c: ml_collections.ConfigDict) -> None:
  """`:tiny` (tests)."""
  s = c.sumo
  s.recordings = ml_collections.ConfigDict(
      {"train": 2, "val": 1, "test": 1, "test_ood": 1, "val_ood": 0}
  )
  s.duration_s = 60.0
  s.held_out.duration_s = 60.0
  s.road_length_m = 900.0
  s.section_length_m = 500.0
  s.warmup_s = 30.0
  c.extraction.control_iterations = 4
