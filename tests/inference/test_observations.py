"""`Observations`: the projection of `Scenarios`, the image frame, the Predictor's input."""

import numpy as np
import pandas as pd
import pytest

from cvmdx_jax.data import extract, frames, highd
from cvmdx_jax.inference import observations as obs_lib
from tests.data.conftest import write_recording
from tests.inference.test_retrace import _random_predictor, _scenarios


def test_a_true_future_mapped_to_the_image_lands_on_the_recorded_centres(tmp_path):
  write_recording(tmp_path, 1)
  rec = highd.read_recording(tmp_path, 1)
  tracks = pd.read_csv(highd.recording_paths(tmp_path, 1)["tracks"]).set_index(["id", "frame"])
  # track 1 drives toward +x changing lanes left, track 3 toward -x changing right
  for track, frame in ((1, 120), (3, 100), (4, 80), (2, 150)):
    row = frames.row_of(rec, track, frame)
    future = extract.windows(rec, np.array([row]))["future"]  # the reader's scenario frame
    image = obs_lib.to_image(obs_lib.from_recording(rec, np.array([row])), future)[0]
    recorded = tracks.loc[[(track, f) for f in range(frame + 1, frame + 126)]]
    expected = np.stack([recorded["x"] + 2.0, recorded["y"] + 1.0], -1)  # 4 m x 2 m boxes
    np.testing.assert_allclose(image, expected, atol=1e-4)  # float32 futures of ~400 m


def test_to_image_by_hand():
  obs = obs_lib.from_arrays(
      **{**_fields(2), "origin": [[100.0, 20.0], [50.0, 10.0]], "direction": [2, 1]}
  )
  xy = np.array([[[1.0, 0.5]], [[1.0, 0.5]]])  # 1 m ahead, 0.5 m to the left
  np.testing.assert_allclose(obs_lib.to_image(obs, xy), [[[101.0, 19.5]], [[49.0, 10.5]]])


def test_scenarios_project_onto_their_observed_part_without_an_image_frame():
  scenarios = _scenarios(3)
  obs = obs_lib.from_scenarios(scenarios)
  for name in ("xi", "mask", "v0", "psi0", "track_id", "frame"):
    np.testing.assert_array_equal(getattr(obs, name), getattr(scenarios, name))
  assert (obs.direction == 0).all() and np.isnan(obs.origin).all()
  with pytest.raises(ValueError, match="without an image frame"):
    obs_lib.to_image(obs, np.zeros((3, 125, 2)))


def test_validate_names_the_field():
  with pytest.raises(ValueError, match="field 'origin' holds NaN"):
    obs_lib.from_arrays(
        **{**_fields(2), "origin": [[0.0, np.nan], [0.0, 0.0]], "direction": [2, 2]}
    )
  with pytest.raises(ValueError, match="field 'xi' has shape"):
    obs_lib.from_arrays(**{**_fields(2), "xi": np.zeros((2, 9, 74, 4))})


def test_predictor_gives_observations_what_it_gives_their_scenarios():
  predictor = _random_predictor(chunk_size=4)
  scenarios = _scenarios(5)
  from_scenarios = predictor(scenarios, seed=3)
  from_obs = predictor(obs_lib.from_scenarios(scenarios), seed=3)
  np.testing.assert_array_equal(
      from_obs.prediction.trajectories, from_scenarios.prediction.trajectories
  )
  # noise_ids (i,) are the default draws; other ids draw other noise
  same = predictor(scenarios, seed=3, noise_ids=np.arange(5)[:, None])
  np.testing.assert_array_equal(
      same.prediction.trajectories, from_scenarios.prediction.trajectories
  )
  other = predictor(scenarios, seed=3, noise_ids=np.arange(5)[:, None] + 7)
  assert not np.allclose(other.prediction.controls, from_scenarios.prediction.controls)
  with pytest.raises(ValueError, match="noise_ids"):
    predictor(scenarios, noise_ids=np.arange(4)[:, None])


def _fields(m: int) -> dict:
  return {
      "xi": np.zeros((m, 9, 75, 4)),
      "mask": np.ones((m, 9, 75), bool),
      "v0": np.full(m, 30.0),
      "psi0": np.zeros(m),
  }
