"""Dataset settings for experiments/make_dataset.py.

Run: `PYTHONPATH=. .venv/bin/python experiments/make_dataset.py --config=configs/dataset.py
--data_dir=data/sumo` (presets `:small`, `:tiny`; other sources with
`--config.source=highd --config.highd_dir=/path/to/highD/data` or
`--config.source=cvmd_mat --config.mat_dir=/path/with/train_and_test`).

Default (SUMO): 4 recordings of 10 simulated minutes on a 1 km, 3+3-lane section; recordings
1-3 train, 4 test; class-balanced, >= 9,000 train and >= 3,000 test scenarios.
"""

import ml_collections

# highD split by recording (fixed): test = ids ending in 3, 6 or 9 (18 of 60, ~30 %).
HIGHD_TEST = tuple(i for i in range(1, 61) if i % 10 in (3, 6, 9))
HIGHD_TRAIN = tuple(i for i in range(1, 61) if i not in HIGHD_TEST)


def get_config(preset: str = "default") -> ml_collections.ConfigDict:
  """preset: 'default', 'small' or 'tiny'."""
  c = ml_collections.ConfigDict()
  c.source = "sumo"  # sumo | highd | cvmd_mat
  c.seed = 0  # SUMO seeds and balancing draw
  c.highd_dir = ""  # directory with XX_tracks.csv etc. (source=highd)
  c.mat_dir = ""  # directory with train/ and test/ class folders (source=cvmd_mat)
  # Fixed split by recording id (source sumo / highd).
  c.splits = ml_collections.ConfigDict()
  c.splits.train = (1, 2, 3)
  c.splits.test = (4,)

  c.extraction = ml_collections.ConfigDict()
  c.extraction.lc_offsets_s = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5)  # s before crossing
  c.extraction.kl_stride_s = 1.0  # s between keep-lane windows of one track
  c.extraction.balance = True  # undersample each class to the smallest one
  c.extraction.seed = 0  # balancing draw
  c.extraction.control_smoothing = 1e-2  # control-difference penalty of the controls fit
  c.extraction.control_iterations = 8  # Gauss-Newton steps of the controls fit

  c.sumo = ml_collections.ConfigDict()
  c.sumo.seed = 0  # SUMO seed = seed * 1000 + recording id
  c.sumo.num_recordings = 4  # recordings 1..num_recordings
  c.sumo.workers = 2  # SUMO processes at once
  c.sumo.lanes = 3  # lanes per carriageway
  c.sumo.lane_width_m = 3.75
  c.sumo.median_m = 2.0  # gap between the carriageways
  c.sumo.road_length_m = 1400.0  # simulated road
  c.sumo.section_start_m = 250.0  # visible ("recorded") section start
  c.sumo.section_length_m = 1000.0  # visible section (highD sees ~420 m)
  c.sumo.image_top_m = 8.0  # image y of the northern road edge
  c.sumo.speed_limit_ms = 36.11  # road speed (130 km/h); types scale it by speedFactor
  c.sumo.warmup_s = 60.0  # simulated before frame 1
  c.sumo.duration_s = 600.0  # recorded time per recording
  c.sumo.flow_veh_per_hour = 2400.0  # Poisson arrivals per carriageway
  c.sumo.lateral_resolution = 0.8  # sublane width, m

  if preset == "small":
    c.sumo.duration_s = 200.0
  elif preset == "tiny":
    c.sumo.duration_s = 60.0
    c.sumo.road_length_m = 900.0
    c.sumo.section_length_m = 500.0
    c.sumo.warmup_s = 30.0
    c.extraction.control_iterations = 4
  elif preset != "default":
    raise ValueError(f"configs/dataset.py: unknown preset '{preset}' (default, small, tiny)")
  return c
