"""Per-recording SUMO plans: split numbering, ranges, the held-out road, determinism, and
the vTypes written for SUMO."""

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from configs import dataset as dataset_config
from cvmdx_jax.data import sumo_network, sumo_plan


def _sumo(preset=""):
  return dataset_config.get_config(preset).sumo


@pytest.mark.parametrize("preset", ["", "small", "tiny"])
def test_splits_are_disjoint_consecutive_and_complete(preset):
  cfg = _sumo(preset)
  ids = sumo_plan.split_ids(cfg)
  assert list(ids) == ["train", "val", "test", "test_ood", "val_ood"]
  flat = [i for name in ids for i in ids[name]]
  assert flat == list(range(1, len(flat) + 1))  # each id once, numbered 1.. in split order
  assert all(len(ids[name]) >= 1 for name in ids if name != "val_ood")
  assert len(ids["val_ood"]) == (0 if preset == "tiny" else 1)
  plans = sumo_plan.plans(cfg)
  assert {p.split for p in plans.values()} == {name for name in ids if ids[name]}
  for name, members in ids.items():
    assert all(plans[i].split == name for i in members)


def test_default_sizes_of_the_presets():
  counts = {
      preset: {k: len(v) for k, v in sumo_plan.split_ids(_sumo(preset)).items()}
      for preset in ("", "small", "tiny")
  }
  assert counts[""] == {"train": 10, "val": 2, "test": 3, "test_ood": 2, "val_ood": 1}
  assert counts["small"] == {"train": 12, "val": 2, "test": 2, "test_ood": 1, "val_ood": 1}


def test_val_ood_renumbers_no_other_recording():
  """val_ood is numbered last: the recordings (and their plans) of the other splits are those
  of the same config without it."""
  cfg = _sumo("small")
  without = _sumo("small")
  without.recordings.val_ood = 0
  plans, before = sumo_plan.plans(cfg), sumo_plan.plans(without)
  assert set(plans) - set(before) == set(sumo_plan.split_ids(cfg)["val_ood"])
  assert all(plans[i] == before[i] for i in before)


@pytest.mark.parametrize("preset", ["", "small", "tiny"])
def test_held_out_road_is_in_no_other_split(preset):
  cfg = _sumo(preset)
  plans = sumo_plan.plans(cfg).values()
  seen = [p for p in plans if p.split not in sumo_plan.HELD_OUT_ROADS]
  held = [p for p in plans if p.split == "test_ood"]
  assert held
  for p in held:
    assert p.road == sumo_plan.Road(4, 3.5, 110.0 / 3.6)
    assert all(
        p.road.lanes != q.road.lanes
        and p.road.lane_width_m != q.road.lane_width_m
        and p.road.speed_limit_ms != q.road.speed_limit_ms
        for q in seen
    )
    assert p.flow_veh_per_hour > max(q.flow_veh_per_hour for q in seen)
    assert 700 <= p.flow_per_lane <= 900


@pytest.mark.parametrize("preset", ["", "small"])
def test_val_ood_road_is_in_no_other_split(preset):
  """The val_ood road: lane width and speed limit of no train / val / test recording, and not
  the test_ood road."""
  plans = sumo_plan.plans(_sumo(preset)).values()
  seen = [p for p in plans if p.split not in sumo_plan.HELD_OUT_ROADS]
  ood = {p.road for p in plans if p.split == "test_ood"}
  held = [p for p in plans if p.split == "val_ood"]
  assert held
  for p in held:
    assert p.road == sumo_plan.Road(3, 3.5, 90.0 / 3.6) and p.road not in ood
    assert all(
        p.road.lane_width_m != q.road.lane_width_m
        and p.road.speed_limit_ms != q.road.speed_limit_ms
        for q in seen
    )
    assert 800 <= p.flow_per_lane <= 1000


def test_every_split_with_two_recordings_has_both_lane_counts():
  plans = sumo_plan.plans(_sumo())
  for name in ("train", "val", "test"):
    lanes = [p.road.lanes for p in plans.values() if p.split == name]
    assert sorted(set(lanes)) == [2, 3], name
    assert lanes[0] == 3  # (3, 2) cycled within the split


def test_draws_lie_in_the_documented_ranges():
  cfg = _sumo()
  plans = sumo_plan.plans(cfg).values()
  for p in plans:
    assert np.isclose(sum(t.probability for t in p.types), 1.0)
    assert np.isclose(sum(t.probability for t in p.types if t.vclass == "Truck"), p.truck_share)
    assert 0.1 <= p.truck_share <= 0.3
    assert p.car_following in ("Krauss", "IDM")
    assert [t.vclass for t in p.types] == ["Car"] * 3 + ["Truck"] * 2
    if p.split not in sumo_plan.HELD_OUT_ROADS:
      assert 500 <= p.flow_per_lane <= 1000 and p.road.lane_width_m == 3.75
      assert round(p.road.speed_limit_ms * 3.6) in (100, 120, 130)
    for t in p.types:
      ranges = (cfg.car if t.vclass == "Car" else cfg.truck).to_dict()
      for key, (lo, hi) in ranges.items():
        value = t.desired_max_speed_ms * 3.6 if key == "desired_max_speed_kmh" else getattr(t, key)
        assert lo - 1e-9 <= value <= hi + 1e-9, (t.name, key, value)
  # Recordings differ: both car-following models, several speed limits and spread drivers.
  assert {p.car_following for p in plans} == {"Krauss", "IDM"}
  gains = [t.lc_speed_gain for p in plans for t in p.types if t.vclass == "Car"]
  assert max(gains) / min(gains) > 2.5


def test_plans_are_deterministic_under_the_seed():
  a, b = sumo_plan.plans(_sumo()), sumo_plan.plans(_sumo())
  assert a == b
  other = _sumo()
  other.seed = 1
  c = sumo_plan.plans(other)
  assert all(a[i] != c[i] for i in a)
  # A recording's plan depends on its id and split position, not on how many others exist.
  fewer = _sumo()
  fewer.recordings.test_ood = 1
  assert sumo_plan.plans(fewer)[1] == a[1]


def test_routes_carry_the_plan(tmp_path):
  cfg = _sumo()
  plan = sumo_plan.plans(cfg)[2]
  root = ET.parse(sumo_network.write_routes(cfg, plan, tmp_path, "r")).getroot()
  vtypes = root.find("vTypeDistribution").findall("vType")
  assert [v.get("id") for v in vtypes] == [t.name for t in plan.types]
  for v, t in zip(vtypes, plan.types):
    assert v.get("carFollowModel") == plan.car_following
    for field, attr in (
        ("accel", "accel"),
        ("decel", "decel"),
        ("sigma", "sigma"),
        ("tau", "tau"),
        ("lc_speed_gain", "lcSpeedGain"),
        ("lc_keep_right", "lcKeepRight"),
        ("max_speed_lat", "maxSpeedLat"),
        ("lc_accel_lat", "lcAccelLat"),
        ("length_m", "length"),
    ):
      assert float(v.get(attr)) == pytest.approx(getattr(t, field), abs=5e-3)
    assert v.get("speedFactor").startswith(f"normc({t.speed_factor:.3f},")
    assert (v.get("desiredMaxSpeed") is None) == (t.vclass == "Car")
  flows = root.findall("flow")
  assert [f.get("from") for f in flows] == ["E", "W"]
  rate = float(flows[0].get("period")[4:-1])  # exp(rate), vehicles per second
  assert rate == pytest.approx(plan.flow_per_lane * plan.road.lanes / 3600, rel=1e-3)
  assert float(flows[0].get("end")) == cfg.warmup_s + plan.duration_s


def test_unknown_range_key_is_named():
  cfg = _sumo()
  cfg.car.wheelbase = (2.0, 3.0)
  with pytest.raises(ValueError, match="sumo.car"):
    sumo_plan.plans(cfg)
