"""Metrics against hand-worked values."""

import numpy as np

from cvmdx_jax.evaluation import metrics


def _line(dx, dy, t=125):
  return np.stack([np.full(t, dx), np.full(t, dy)], -1).astype(np.float32)


def test_ade_fde_by_hand():
  gt = np.zeros((125, 2), np.float32)
  pred = np.stack([np.linspace(0, 4, 125), np.zeros(125)], -1).astype(np.float32)
  assert np.isclose(metrics.ade(pred, gt), 2.0, atol=1e-5)
  assert np.isclose(metrics.fde(pred, gt), 4.0)
  assert np.isclose(metrics.fde(_line(3, 4), gt), 5.0)


def test_min_k_masks_unused_slots():
  gt = np.zeros((125, 2), np.float32)
  hyps = np.stack([_line(3, 4), _line(0, 1), _line(0, 0)])  # slot 2 perfect but unused
  valid = np.array([True, True, False])
  assert np.isclose(metrics.min_ade_k(hyps, gt, valid), 1.0)
  assert np.isclose(metrics.min_fde_k(hyps, gt, valid), 1.0)


def test_most_likely_and_rates():
  gt = np.zeros((2, 125, 2), np.float32)
  hyps = np.stack(
      [
          np.stack([_line(0, 2.5), _line(1, 0), _line(0, 0)]),
          np.stack([_line(0, 1), _line(5, 0), _line(0, 0)]),
      ]
  )
  probs = np.array([[0.3, 0.7, 0.0], [0.6, 0.4, 0.0]], np.float32)
  ml = np.asarray(metrics.most_likely(hyps, probs))
  np.testing.assert_allclose(ml[0], _line(1, 0))
  np.testing.assert_allclose(ml[1], _line(0, 1))
  mean = np.stack([_line(0, 2.0), _line(0, 1.0)])
  np.testing.assert_allclose(metrics.fde(mean, gt), [2.0, 1.0])
  np.testing.assert_allclose(metrics.ade(ml, gt), [1.0, 1.0])
  valid = probs > 0
  np.testing.assert_allclose(metrics.min_fde_k(hyps, gt, valid), [1.0, 1.0])
  np.testing.assert_allclose(metrics.hit(mean, gt), [0.0, 1.0])  # lateral 2.0 m vs 1.0 m
  np.testing.assert_allclose(metrics.miss(metrics.min_fde_k(hyps, gt, valid)), [0.0, 0.0])
  np.testing.assert_allclose(metrics.miss(metrics.min_fde_k(hyps + 3, gt, valid)), [1.0, 1.0])


def test_final_lon_lat_by_hand():
  gt = np.zeros((125, 2), np.float32)
  lon, lat = metrics.final_lon_lat(_line(-3, 4), gt)
  assert np.isclose(lon, 3.0) and np.isclose(lat, 4.0)


def test_brier_min_fde_uses_the_probability_of_the_closest_hypothesis():
  gt = np.zeros((125, 2), np.float32)
  hyps = np.stack([_line(3, 4), _line(0, 1), _line(0, 0)])  # slot 2 unused
  probs = np.array([0.8, 0.2, 0.0], np.float32)
  value = metrics.brier_min_fde(hyps, probs, gt, probs > 0)
  assert np.isclose(value, 1.0 + 0.8**2)  # minFDE 1 from slot 1 with p = 0.2


def test_target_lane_hit_needs_enough_probability():
  gt = np.tile(_line(50, 3.5)[None], (2, 1, 1))
  hyps = np.stack(
      [np.stack([_line(50, 0.0), _line(48, 3.0)]), np.stack([_line(50, 0.0), _line(48, 3.0)])]
  )
  probs = np.array([[0.6, 0.4], [0.9, 0.1]], np.float32)
  np.testing.assert_allclose(metrics.target_lane_hit(hyps, probs, gt), [1.0, 0.0])
