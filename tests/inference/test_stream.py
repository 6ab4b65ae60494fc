"""The online predictor (`inference.stream`) against a whole recording's predictions."""

import numpy as np
import pytest

from cvmdx_jax.data import frames, highd
from cvmdx_jax.evaluation import prob_calibration
from cvmdx_jax.inference import observations as obs_lib
from cvmdx_jax.inference import recording, stream
from tests.data.conftest import write_recording
from tests.inference.test_retrace import _random_predictor

PREDICTED = (80, 105, 130, 155, 180, 205, 230)


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
  directory = tmp_path_factory.mktemp("recording")
  write_recording(directory, 1)
  return highd.read_recording(directory, 1)


def _frame_input(rec, frame):
  """What a tracker gives at `frame`: ids, image-frame centres and velocities, neighbours."""
  rows = np.flatnonzero(rec.frame == frame)
  sign = np.where(rec.direction[rows] == 2, 1.0, -1.0)[:, None]
  flip = np.concatenate([sign, -sign], -1)
  return (
      rec.track_id[rows],
      frames.image_centre(rec, rows),
      rec.vel[rows] * flip,
      rec.direction[rows],
      rec.neighbours[rows],
  )


def test_stream_observations_equal_the_recordings(rec):
  history = stream.empty_history()
  for frame in range(1, 301):
    history = stream.update(history, frame, *_frame_input(rec, frame))
    assert history.pos.shape[1] == 75 and len(history.track_id) == np.sum(rec.frame == frame)
    rows = frames.observable_rows(rec, [frame])
    expected = obs_lib.from_recording(rec, rows) if frame >= 75 else None
    got = stream.observations(history, recording_id=1)
    if expected is None:
      assert len(got) == 0
      continue
    for name in (
        "xi",
        "mask",
        "v0",
        "psi0",
        "track_id",
        "frame",
        "recording_id",
        "origin",
        "direction",
    ):
      np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), name)


def test_stream_predictions_equal_a_whole_recordings(rec):
  predictor = _random_predictor(chunk_size=4)
  whole, summary = recording.predict_frames(predictor, rec, PREDICTED, seed=5, every=25)
  online = stream.Stream(predictor, seed=5, recording_id=1)
  parts = []
  for frame in range(1, PREDICTED[-1] + 1):
    out = online.step(frame, *_frame_input(rec, frame), predict=frame in PREDICTED)
    if out is not None:
      parts.append(out)
  for name in ("frame", "track_id", "mean", "means", "probs"):
    np.testing.assert_array_equal(
        np.concatenate([getattr(p, name) for p in parts]), getattr(whole, name), name
    )
  # tracks 1-4 at the 7 frames, track 5 (from frame 100) from frame 174 on: 180, 205, 230
  assert summary["predictions"] == len(whole) == 4 * 7 + 3 and summary["vehicles"] == 5
  assert summary["consistency_m"]["pairs"] == 31 - 5  # each track's first frame has none


def test_the_point_prediction_is_the_samples_mean_whatever_the_p_temperature(rec):
  predictor = prob_calibration.with_temperature(_random_predictor(chunk_size=4), 0.5)
  observations = obs_lib.from_recording(rec, frames.observable_rows(rec, [PREDICTED[0]]))
  preds = recording.predict(predictor, observations, seed=3, samples=True)
  np.testing.assert_allclose(preds.mean, preds.samples.mean(axis=1), atol=1e-3)
  np.testing.assert_allclose(preds.probs.sum(axis=1), 1.0, rtol=1e-6)


def test_a_vehicle_that_disappears_is_dropped_and_a_gap_restarts(rec):
  history = stream.empty_history()
  for frame in range(1, 80):
    ids, centre, vel, direction, nbr = _frame_input(rec, frame)
    keep = ids != 2 if frame == 60 else np.ones(len(ids), bool)  # 2 missing once
    history = stream.update(
        history, frame, ids[keep], centre[keep], vel[keep], direction[keep], nbr[keep]
    )
  assert history.track_id[stream.ready(history)].tolist() == [1, 3, 4]
  history = stream.update(history, 81, *_frame_input(rec, 81))  # frame 80 skipped
  assert not history.valid[:, :-1].any()


def test_temporal_consistency_by_hand():
  means = np.zeros((3, 1, 125, 2))
  means[0, 0, :, 0] = np.arange(125)  # frame 0: x = step
  means[1, 0, :, 0] = np.arange(125) + 5 + 0.5  # frame 5: the same path, 0.5 m ahead
  means[2, 0, :, 0] = 1000.0  # another track
  preds = recording.VehiclePredictions(
      recording_id=np.zeros(3, int),
      frame=np.array([0, 5, 5]),
      track_id=np.array([1, 1, 2]),
      mean=means[:, 0],
      means=means,
      probs=np.ones((3, 1)),
      samples=None,
      out_of_distribution=np.zeros(3, bool),
  )
  np.testing.assert_allclose(recording.temporal_consistency(preds, 5), [0.5])
  assert len(recording.temporal_consistency(preds, 10)) == 0
