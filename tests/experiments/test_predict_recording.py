"""experiments/predict_recording.py: the tidy table, its provenance and animation, and the
one-line errors of bad input."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from cvmdx_jax.data import frames, highd
from cvmdx_jax.inference import recording
from cvmdx_jax.storage import checksums
from tests.data.conftest import write_recording
from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[2]


def _run(*argv):
  return subprocess.run(
      [sys.executable, "experiments/predict_recording.py", *argv],
      cwd=REPO,
      env=environ(JAX_PLATFORMS="cpu"),
      capture_output=True,
      text=True,
      timeout=600,
  )


@pytest.mark.slow  # ~20 s of CPU: a subprocess that compiles the predictor, and the GIF
def test_every_vehicle_of_a_window_lands_in_the_table(tiny_runs, tmp_path):
  data_dir = tiny_runs / "data" / "recordings"
  recording_id = highd.available_recordings(data_dir)[0]
  tracks = highd.recording_paths(data_dir, recording_id)["tracks"]
  out = tmp_path / "pred.csv.gz"
  proc = _run(
      f"--tokenizer_dir={tiny_runs / 'tokenizer'}",
      f"--diffusion_dir={tiny_runs / 'diffusion'}",
      f"--recording={tracks}",
      "--start=5s",
      "--end=6s",
      "--every=10",
      f"--out={out}",
      "--samples",
      "--num_samples=4",
      f"--animation={tmp_path / 'scene.gif'}",
      "--host_devices=2",  # each call's vehicles split over two CPU devices
  )
  assert proc.returncode == 0, proc.stderr[-3000:]
  table = pd.read_csv(out)
  assert tuple(table.columns) == recording.TABLE_COLUMNS
  rec = highd.read_recording(data_dir, recording_id)
  first = frames.frame_range(rec)[0]
  window = list(range(first + 125, first + 151, 10))  # 5 s .. 6 s after the first frame
  rows = frames.observable_rows(rec, window)
  expected = set(zip(rec.frame[rows].tolist(), rec.track_id[rows].tolist()))
  hyps = table[table["kind"] == "hypothesis"]
  assert set(zip(hyps["frame"], hyps["track_id"])) == expected
  first_step = hyps[np.isclose(hyps["t"], 0.04)]
  np.testing.assert_allclose(
      first_step.groupby(["frame", "track_id"])["probability"].sum(), 1.0, atol=1e-3
  )
  samples = table[table["kind"] == "sample"]
  assert len(samples) == len(expected) * 4 * 125
  provenance = json.loads(Path(f"{out}.provenance.json").read_text())
  assert provenance["recording"]["files"]["tracks"]["sha256"] == checksums.file_sha256(tracks)
  assert provenance["summary"]["predictions"] == len(expected)
  assert provenance["window"] == {"start": first + 125, "end": first + 150, "every": 10}
  assert provenance["sampling"]["num_samples"] == 4 and provenance["host_devices"] == 2
  with Image.open(tmp_path / "scene.gif") as gif:
    assert gif.n_frames == len(window)
  assert "predictions_per_second" in proc.stdout and "consistency_m" in proc.stdout


@pytest.mark.parametrize(
    "case",
    [
        "missing_column",
        pytest.param("frame_outside", marks=pytest.mark.slow),
        pytest.param("no_history", marks=pytest.mark.slow),
        pytest.param("missing_file", marks=pytest.mark.slow),
        pytest.param("bad_out", marks=pytest.mark.slow),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, case):
  write_recording(tmp_path, 1)
  tracks = highd.recording_paths(tmp_path, 1)["tracks"]
  args, named = {
      "missing_column": ([], "laneId"),
      "frame_outside": (["--start=400"], "--start=400"),
      "no_history": (["--end=60"], "3 s of history"),
      "missing_file": ([f"--recording={tmp_path / '07_tracks.csv'}"], "07_tracks.csv"),
      "bad_out": ([f"--out={tmp_path / 'out' / 'pred.json'}"], "--out="),
  }[case]
  if case == "missing_column":
    pd.read_csv(tracks).drop(columns="laneId").to_csv(tracks, index=False)
  (tmp_path / "run").mkdir()
  proc = _run(
      f"--tokenizer_dir={tmp_path / 'run'}",
      f"--diffusion_dir={tmp_path / 'run'}",
      f"--recording={tracks}",
      f"--out={tmp_path / 'out' / 'pred.csv.gz'}",
      *args,
  )
  lines = [line for line in proc.stderr.splitlines() if line.strip()]
  assert proc.returncode == 2, proc.stderr
  assert len(lines) == 1 and lines[0].startswith("predict_recording: error: "), proc.stderr
  assert named in lines[0]
  assert not (tmp_path / "out").exists()
