"""The scene, moving (`evaluation.animation`): one GIF frame per recording frame, vehicles
and predicted hypotheses drawn where they are."""

import io

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from cvmdx_jax.data import frames, highd
from cvmdx_jax.evaluation import animation
from cvmdx_jax.inference import recording
from tests.data.conftest import write_recording

FRAMES = (100, 110, 120)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
  directory = tmp_path_factory.mktemp("recording")
  write_recording(directory, 1)
  return highd.read_recording(directory, 1), frames.scene(directory, 1)


def _frames(gif: bytes) -> list[np.ndarray]:
  image = Image.open(io.BytesIO(gif))
  out = []
  for k in range(image.n_frames):
    image.seek(k)
    out.append(np.asarray(image.convert("RGB"), np.int16))
  return out


def _predictions(rec, track: int, frame: int, shift_y: float):
  """One prediction of `track` at `frame`: two hypotheses, its recorded future and the same
  moved by `shift_y` m."""
  rows = np.array([frames.row_of(rec, track, frame)])
  future, _ = frames.futures(rec, rows)
  means = np.stack([future[0], future[0] + [0.0, shift_y]])[None]
  return recording.VehiclePredictions(
      recording_id=np.array([1]),
      frame=np.array([frame]),
      track_id=np.array([track]),
      mean=np.einsum("mc,mctd->mtd", np.array([[0.7, 0.3]]), means),
      means=means,
      probs=np.array([[0.7, 0.3]]),
      samples=None,
      out_of_distribution=np.zeros(1, bool),
  )


def test_one_image_per_frame_and_the_vehicles_move(scene):
  rec, meta = scene
  images = _frames(animation.render_gif(rec, meta, FRAMES))
  assert len(images) == len(FRAMES)
  assert all(np.any(a != b) for a, b in zip(images, images[1:]))


def test_predictions_are_drawn_at_their_frame_only(scene):
  rec, meta = scene
  plain = _frames(animation.render_gif(rec, meta, FRAMES))
  drawn = _frames(animation.render_gif(rec, meta, FRAMES, _predictions(rec, 1, 110, 3.0)))
  assert np.array_equal(plain[0], drawn[0]) and np.array_equal(plain[2], drawn[2])
  changed = np.any(plain[1] != drawn[1], -1)
  # track 1's colour (tab10 orange, 255 127 14), blended over the road by the line's alpha
  red, green, blue = np.moveaxis(drawn[1][changed], -1, 0)
  orange = (red > 200) & (green > 100) & (green < 200) & (blue < 150)
  assert changed.sum() > 200 and orange.mean() > 0.5


def test_no_frames_is_refused(scene):
  with pytest.raises(ValueError, match="no frames"):
    animation.render_gif(*scene, [])


@pytest.mark.slow  # ~10 s of CPU compiling a predictor; make demo runs write_clip too
def test_write_clip_predicts_the_section_and_writes_the_gif(tmp_path):
  from tests.inference.test_retrace import _random_predictor

  write_recording(tmp_path, 1)
  path = tmp_path / "clip.gif"
  # frames 101 .. 126 every 5; the middle 100 m of the road's extent in tracks.csv
  summary = animation.write_clip(
      _random_predictor(chunk_size=4),
      tmp_path,
      1,
      path,
      start_s=4.0,
      seconds=1.0,
      section_m=100.0,
      num_samples=None,
  )
  with Image.open(path) as gif:  # closed here: an open file left to the collector warns
    assert gif.n_frames == 6
  tracks = pd.read_csv(highd.recording_paths(tmp_path, 1)["tracks"])
  centre = tracks["x"] + 2.0
  middle = (centre.min() + centre.max()) / 2
  in_clip = tracks[
      tracks["frame"].isin(range(101, 127, 5))
      & (tracks["frame"] - tracks.groupby("id")["frame"].transform("min") >= 74)
      & ((tracks["x"] + 2.0 - middle).abs() <= 50.0)
  ]
  assert summary["predictions"] == len(in_clip) > 0
