"""experiments/region_groups.py on the session's tiny runs: every candidate's row, each
recording's coverage, and the errors computed from them."""

import json

import numpy as np
import pytest

from cvmdx_jax.data import dataset
from cvmdx_jax.evaluation import region_groups
from tests.subprocess_env import run_script


def test_rows_per_candidate_and_recording(tiny_runs, tmp_path):
  splits = ("val", "test", "test_ood")  # one recording each in the tiny data
  workdir = tmp_path / "new" / "workdir"  # created with its parents
  proc = run_script(
      "region_groups",
      f"--run={tiny_runs}",
      "--denoiser=diffusion",
      f"--data_dir={tiny_runs / 'data'}",
      f"--splits={','.join(splits)}",
      "--max_scenarios=0",
      f"--workdir={workdir}",
  )
  assert proc.returncode == 0, proc.stderr
  rows = json.loads((workdir / "region_groups.json").read_text())["rows"]
  assert [r["candidate"] for r in rows] == ["plain", *region_groups.COVARIATES]
  recordings = sorted(
      int(i)
      for s in splits
      for i in np.unique(dataset.load_split(tiny_runs / "data", s).recording_id)
  )
  for row in rows:
    assert [r["id"] for r in row["recordings"]] == recordings
    cover = np.array([r["coverage"] for r in row["recordings"]])
    assert cover.shape == (len(recordings), 5) and np.all((cover >= 0) & (cover <= 1))
    counts = [r["scenarios"] for r in row["recordings"]]
    assert (row["mean_error"], row["largest_error"]) == pytest.approx(
        region_groups.errors(counts, cover)
    )
  assert (workdir / "region_groups.md").read_text() in proc.stdout


def test_one_recording_is_refused_before_any_prediction(tiny_runs, tmp_path):
  proc = run_script(
      "region_groups",
      f"--run={tiny_runs}",
      "--denoiser=diffusion",
      f"--data_dir={tiny_runs / 'data'}",
      "--splits=val",
      f"--workdir={tmp_path / 'w'}",
  )
  assert proc.returncode != 0
  assert "--data_dir / --splits: 1 recording(s)" in proc.stderr
  assert not (tmp_path / "w" / "predictions").exists()
