"""The quality benchmark's evaluation on a toy world whose true distribution is known.

Futures are constant velocity plus a lateral offset a * (t / 5 s)^2 with a ~ N(3 (c - 1),
1.5^2) m for class c (known from the observation: the fake model reads the label);
the fake "cVMDx" samples from exactly that distribution, so it must beat constant velocity
on the proper scores, and its regions calibrated on val must cover ~90 % on test.
"""

import types

import numpy as np
import pytest

from cvmdx_jax import constants
from cvmdx_jax.data import from_arrays
from cvmdx_jax.evaluation import quality, quality_tables

SPREAD_M = 1.5
N = 8


def _world(m, seed):
  rng = np.random.default_rng(seed)
  speed = rng.uniform(20.0, 30.0, m)
  xi = np.zeros((m, constants.NUM_VEHICLES, constants.T_OBS, 4), np.float32)
  xi[:, 0, :, 2] = speed[:, None]
  mask = np.zeros(xi.shape[:3], bool)
  mask[:, 0] = True
  t = constants.DT * np.arange(1, constants.T_PRED + 1)
  shape = (t / t[-1]) ** 2
  label = np.arange(m) % 3
  offset = 3.0 * (label[:, None] - 1) + rng.normal(0, SPREAD_M, (m, 1))
  future = np.stack([speed[:, None] * t, offset * shape], -1)
  scen = from_arrays(
      xi=xi,
      mask=mask,
      future=future,
      controls=np.zeros_like(future),
      v0=speed,
      psi0=np.zeros(m),
      label=label,
      recording_id=1 + (np.arange(m) >= m // 3),  # two recordings
      track_id=np.arange(m) // 2,
  )
  return scen, shape


def _fake_predictor(shape):
  def predict(scenarios, seed=0):
    m = len(scenarios)
    rng = np.random.default_rng(seed + m)
    t = constants.DT * np.arange(1, constants.T_PRED + 1)
    lon = np.broadcast_to(scenarios.v0[:, None, None] * t, (m, N, len(t)))
    centre = 3.0 * (scenarios.label[:, None, None] - 1.0)
    lat = (centre + rng.normal(0, SPREAD_M, (m, N, 1))) * shape
    traj = np.stack([lon, lat], -1).astype(np.float32)
    hyp = types.SimpleNamespace(
        means=traj[:, :3],
        probs=np.full((m, 3), 1 / 3, np.float32),
        labels=np.arange(N)[None].repeat(m, 0) % 2,  # two clusters of the same distribution
    )
    return types.SimpleNamespace(
        prediction=types.SimpleNamespace(trajectories=traj),
        hypotheses=hyp,
        q=np.zeros(m, int),
        delta=rng.uniform(0, 1, m).astype(np.float32),
    )

  return predict


@pytest.mark.slow  # ~20 jit compilations of the scorers: 95 s on the shared 2-core CPU (load 19)
def test_true_distribution_wins_and_calibrated_regions_cover():
  val, shape = _world(300, 0)
  test, _ = _world(300, 1)
  calibration = (_world(300, 2)[0], _world(300, 3)[0])  # pooled: 600 scenarios
  lines = []
  runs = {
      "r0": quality.evaluate_run(
          _fake_predictor(shape), None, None, val, {"test": test}, calibration, log=lines.append
      )
  }
  assert any(line.startswith("  calibration (600): cvmdx_samples") for line in lines)
  table = quality_tables.summary(runs, "test")
  assert table["cvmdx_samples"]["energy_score"] < table["cv"]["energy_score"]
  assert table["cvmdx_samples"]["nll_5s"] < table["cv"]["nll_5s"]
  row = runs["r0"].splits["test"]["cvmdx_samples"]
  for s in (1, 3, 5):
    assert abs(np.mean(row[f"cal_cover_{s}s"]) - 0.9) < 0.06
    assert abs(np.mean(row[f"online_cover_{s}s"]) - 0.9) < 0.03  # the bound: 0.02 + delay 0
    assert np.all(row[f"online_area_{s}s"] > 0)
  diffs = {
      (d["a"], d["b"], d["metric"], d["subset"]): d
      for d in quality_tables.differences(runs, "test")
  }
  assert diffs[("cvmdx_samples", "cv", "energy_score", "all")]["by_seed"]["r0"]["verdict"] == (
      "better"
  )
  assert "| cvmdx_samples - cv | energy_score | all |" in quality_tables.difference_table(
      list(diffs.values())
  )
  assert "cVMDx, N samples" in quality_tables.calibration_table(runs, ["test"])
  assert "| cVMDx, N samples | test | " in quality_tables.online_table(runs, ["test"])
  by_recording = quality_tables.recording_table(runs, ["test"]).splitlines()[2:]
  assert [line.split(" | ")[1:3] for line in by_recording] == [["1", "100"], ["2", "200"]]
  covered = sum(int(line.split(" | ")[2]) * float(line.split(" | ")[3]) for line in by_recording)
  assert covered == pytest.approx(np.sum(row["cal_cover_1s"]), abs=0.2)  # 3 decimals


def test_stream_times_put_recordings_one_after_another():
  scen = types.SimpleNamespace(
      recording_id=np.array([7, 3, 7, 3]), frame=np.array([10, 500, 0, 20])
  )
  times, per_s = quality.stream_times(scen)
  assert per_s == constants.FRAME_RATE_HZ
  # recording 3 first; recording 7 starts after 500 + every truth of recording 3
  assert list(np.argsort(times)) == [3, 1, 2, 0]
  assert times[2] - times[1] > constants.T_PRED
  unknown = types.SimpleNamespace(recording_id=np.array([1, 1]), frame=np.array([-1, 4]))
  np.testing.assert_array_equal(quality.stream_times(unknown)[0], [0, 1])
  assert quality.stream_times(unknown)[1] == 0
