"""highD reader + extraction on the hand-built recording of conftest.py (known answers)."""

import numpy as np
import pytest

from cvmdx_jax import constants, vmm
from cvmdx_jax.data import extract, highd

SLOT = {name: i for i, name in enumerate(constants.VEHICLE_SLOTS)}
CONFIG = extract.ExtractionConfig(lc_offsets_s=(1.0,), kl_stride_s=1.0, balance=False)


@pytest.fixture
def scen(highd_dir):
  return highd.load_scenarios(highd_dir, [1], CONFIG)


def _one(scen, track, frame):
  index = np.flatnonzero((scen.track_id == track) & (scen.frame == frame))
  assert len(index) == 1, (track, frame)
  return scen.take(index[0])


def test_left_lane_change_direction_2(scen):
  s = _one(scen, 1, 126)  # first frame in lane 6 is 151, offset 1 s = 25 frames
  assert s.label == 2 and s.time_to_lane_change == pytest.approx(1.0)
  np.testing.assert_allclose(s.xi[SLOT["ego"], -1], [0, 0, 30, 0], atol=0.02)
  np.testing.assert_allclose(s.xi[SLOT["ego"], 0, :2], [-74 * 0.04 * 30, 0], atol=0.02)
  # Preceding: 20 m + 0.5 * 1 m/s^2 * (5 s)^2 ahead, speed 35 m/s, same lane.
  np.testing.assert_allclose(s.xi[SLOT["preceding"], -1], [32.5, 0, 35, 0], atol=0.05)
  # Right follower: 15 m behind, one lane (4 m) to the right = negative y; exists from 100.
  np.testing.assert_allclose(s.xi[SLOT["rightFollowing"], -1, :2], [-15, -4], atol=0.02)
  expected_mask = np.arange(52, 127) >= 100
  np.testing.assert_array_equal(s.mask[SLOT["rightFollowing"]], expected_mask)
  assert not s.xi[SLOT["rightFollowing"], ~expected_mask].any()
  for slot in ("following", "leftPreceding", "leftAlongside", "rightAlongside"):
    assert not s.mask[SLOT[slot]].any() and not s.xi[SLOT[slot]].any()
  np.testing.assert_allclose(s.future[-1], [150, 4], atol=0.02)  # left = +y
  assert s.v0 == pytest.approx(30, abs=0.01) and s.psi0 == pytest.approx(0, abs=1e-3)


def test_right_lane_change_direction_1(scen):
  s = _one(scen, 3, 116)  # drives toward -x; first frame in lane 2 is 141
  assert s.label == 1 and s.time_to_lane_change == pytest.approx(1.0)
  np.testing.assert_allclose(s.xi[SLOT["ego"], -1], [0, 0, 25, 0], atol=0.02)
  np.testing.assert_allclose(s.xi[SLOT["ego"], 0, :2], [-74 * 0.04 * 25, 0], atol=0.02)
  np.testing.assert_allclose(s.xi[SLOT["leftAlongside"], -1], [0, 4, 25, 0], atol=0.02)
  np.testing.assert_allclose(s.future[-1], [125, -4], atol=0.02)  # right = -y
  # At the crossing frame 141 (future step 25) the ego is 4 * 21 / 41 m to the right.
  assert s.future[24, 1] == pytest.approx(-4 * 21 / 41, abs=0.02)


def test_keep_lane_windows_and_labels(scen):
  lead = scen.take(scen.track_id == 2)
  assert len(lead) > 0 and np.all(lead.label == 0)
  assert np.all(lead.time_to_lane_change == -1)
  ego_kl = scen.take((scen.track_id == 1) & (scen.label == 0))
  assert np.all(ego_kl.frame >= 151)  # no lane change in (t0, t0 + 125]
  assert set(np.unique(scen.recording_id)) == {1}


def test_controls_reproduce_future_and_closed_form(scen):
  pred = np.asarray(vmm.rollout(scen.controls, scen.v0, scen.psi0))
  ade = np.linalg.norm(pred - scen.future, axis=-1).mean(-1)
  assert ade.max() < 0.03
  lead = scen.take(scen.track_id == 2)  # x = x0 + v t + t^2 / 2: a_x = 1, no yaw
  np.testing.assert_allclose(lead.controls[:, 5:-5, 0], 1.0, atol=0.05)
  np.testing.assert_allclose(lead.controls[..., 1], 0.0, atol=1e-3)


def test_balance_equalises_classes(highd_dir):
  cfg = extract.ExtractionConfig(lc_offsets_s=(0.5, 1.0, 2.0), balance=True, seed=3)
  s = highd.load_scenarios(highd_dir, [1, 2], cfg)
  counts = np.bincount(s.label, minlength=3)
  assert counts[0] == counts[1] == counts[2] == 6  # 3 offsets x 2 recordings per class
  again = highd.load_scenarios(highd_dir, [1, 2], cfg)
  np.testing.assert_array_equal(s.frame, again.frame)
