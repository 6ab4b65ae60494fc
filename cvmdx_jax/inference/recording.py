"""Predictions of vehicles in a recording's image frame: the tidy table and temporal
consistency.

`predict` runs a `Predictor` on `Observations` with each vehicle's noise drawn from
(frame, track id), so a vehicle's prediction at a frame does not depend on which other
vehicles and frames share its batch (`inference.stream` predicts frame by frame, a whole
recording is predicted in large batches; both give the same draws).
"""

import dataclasses
import io
import time
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from cvmdx_jax.data import frames as frames_lib
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference import observations as obs_lib
from cvmdx_jax.storage import atomic

TABLE_COLUMNS = (
    "recording",
    "frame",
    "track_id",
    "kind",
    "hypothesis",
    "probability",
    "t",
    "x",
    "y",
)
TABLE_FORMATS = (".parquet", ".csv.gz")


@dataclasses.dataclass(frozen=True)
class VehiclePredictions:
  """Predictions of M (vehicle, frame) pairs in the image frame (numpy).

  Attributes:
    recording_id, frame, track_id: (M,) provenance of each prediction's t0.
    mean: (M, 125, 2) the mean of the sampled trajectories (the point prediction), m.
    means: (M, C, 125, 2) hypothesis mean trajectories, image-frame centres, m.
    probs: (M, C) hypothesis probabilities (0 for empty slots; each row sums to 1; with a
      p(c) temperature other than 1, sum_c p_c means_c is not `mean`).
    samples: (M, N, 125, 2) sampled trajectories in the image frame, or None.
    out_of_distribution: (M,) bool, the tokeniser's uncertainty beyond its training range.
  """

  recording_id: np.ndarray
  frame: np.ndarray
  track_id: np.ndarray
  mean: np.ndarray
  means: np.ndarray
  probs: np.ndarray
  samples: np.ndarray | None
  out_of_distribution: np.ndarray

  def __len__(self) -> int:
    return len(self.frame)


def concatenate(parts) -> VehiclePredictions:
  """`VehiclePredictions` of a sequence of them, along M."""
  return VehiclePredictions(
      **{
          f.name: None
          if getattr(parts[0], f.name) is None
          else np.concatenate([getattr(p, f.name) for p in parts])
          for f in dataclasses.fields(VehiclePredictions)
      }
  )


def noise_ids(observations: obs_lib.Observations) -> np.ndarray:
  """(M, 2) the (frame, track id) each observation's noise is drawn from."""
  return np.stack([observations.frame, observations.track_id], -1).astype(np.int64)


def predict(
    predictor, observations: obs_lib.Observations, seed: int = 0, samples: bool = False
) -> VehiclePredictions:
  """`predictor` (a `Predictor`) on `observations` (with an image frame: `data.frames`,
  `inference.stream`), mapped to the recording's image frame."""
  out = predictor(observations, seed=seed, noise_ids=noise_ids(observations))
  hyp = out.hypotheses
  to_image = lambda xy: obs_lib.to_image(observations, np.asarray(xy))
  return VehiclePredictions(
      recording_id=np.asarray(observations.recording_id),
      frame=np.asarray(observations.frame),
      track_id=np.asarray(observations.track_id),
      mean=to_image(out.prediction.mean),
      means=to_image(hyp.means),
      probs=np.asarray(hyp.probs, np.float64),
      samples=to_image(out.prediction.trajectories) if samples else None,
      out_of_distribution=np.asarray(out.out_of_distribution),
  )


def table(preds: VehiclePredictions) -> pd.DataFrame:
  """The tidy table: one row per (prediction, hypothesis or sample, step), columns
  `TABLE_COLUMNS`; kind "hypothesis" (empty slots left out) or "sample" (probability
  1 / N); t in s after the prediction's frame; x, y image-frame centres, m."""
  parts = [_rows(preds, "hypothesis", preds.means, preds.probs)]
  if preds.samples is not None:
    n = preds.samples.shape[1]
    parts.append(_rows(preds, "sample", preds.samples, np.full((len(preds), n), 1.0 / n)))
  return pd.concat(parts, ignore_index=True)


def _rows(preds, kind: str, paths: np.ndarray, probs: np.ndarray) -> pd.DataFrame:
  m, slot = np.nonzero(probs > 0)
  steps = paths.shape[2]
  rep = lambda x: np.repeat(x, steps)
  xy = paths[m, slot].reshape(-1, 2)
  return pd.DataFrame(
      {
          "recording": rep(preds.recording_id[m]),
          "frame": rep(preds.frame[m]),
          "track_id": rep(preds.track_id[m]),
          "kind": kind,
          "hypothesis": rep(slot),
          "probability": rep(probs[m, slot]),
          "t": np.tile(obs_lib.horizon_s(), len(m)),
          "x": xy[:, 0],
          "y": xy[:, 1],
      }
  )


def check_table_path(path) -> None:
  """UserError naming `path` unless it ends in .parquet (with pyarrow importable) or
  .csv.gz."""
  name = str(path)
  if not name.endswith(TABLE_FORMATS):
    raise UserError(f"--out={name}: expected a file ending in {' or '.join(TABLE_FORMATS)}")
  if name.endswith(".parquet"):
    try:
      import pyarrow  # noqa: F401  (optional: Parquet only where it is installed)
    except ImportError as err:
      raise UserError(
          f"--out={name}: Parquet needs pyarrow, which is not installed; " "write .csv.gz"
      ) from err


def write_table(frame: pd.DataFrame, path) -> None:
  """Writes `frame` atomically as Parquet or gzip-compressed CSV (by `path`'s suffix)."""
  check_table_path(path)
  buffer = io.BytesIO()
  if str(path).endswith(".parquet"):
    frame.to_parquet(buffer, index=False)
  else:
    frame.to_csv(
        buffer, index=False, float_format="%.4f", compression={"method": "gzip", "mtime": 0}
    )
  atomic.write_bytes(Path(path), buffer.getvalue())


def temporal_consistency(preds: VehiclePredictions, step: int) -> np.ndarray:
  """Change between consecutive predictions of one vehicle: for each prediction at frame f
  with one of the same track at f + `step` (frames, < 125), the mean distance (m) between
  their means (`VehiclePredictions.mean`) over the steps both cover (times f + step + 1 ..
  f + 125). Returns (P,) one value per such pair."""
  mean = preds.mean
  horizon = mean.shape[1]
  if not 0 < step < horizon:
    raise ValueError(f"temporal_consistency: step {step} not in 1..{horizon - 1}")
  key = {
      (int(r), int(t), int(f)): i
      for i, (r, t, f) in enumerate(zip(preds.recording_id, preds.track_id, preds.frame))
  }
  pairs = [(i, key[(r, t, f + step)]) for (r, t, f), i in key.items() if (r, t, f + step) in key]
  if not pairs:
    return np.zeros(0)
  first, second = np.asarray(pairs).T
  change = np.linalg.norm(mean[first, step:] - mean[second, : horizon - step], axis=-1)
  return change.mean(-1)


def predict_frames(
    predictor,
    rec,
    frames,
    seed: int = 0,
    samples: bool = False,
    every: int | None = None,
    section=None,
) -> tuple[VehiclePredictions, dict]:
  """Every vehicle with 3 s of history at each of `frames` of recording `rec`
  (`data.highd.Recording`; with `section` (x0, x1) only those whose image-frame centre x
  lies in it), in batches of `predictor.scenarios_per_call` over vehicles and frames (observations
  built per batch; only the hypotheses, and the samples if asked, are kept).

  Returns:
    (predictions, summary): summary = {"predictions", "vehicles", "frames", "seconds"
    (wall clock, first compilation included), "cpu_seconds" (the process's, all threads),
    "predictions_per_second" (wall clock), "out_of_distribution", "consistency_m" (mean
    and median of `temporal_consistency` at `every` frames, where 0 < every < 125)}; the
    predictions are in the order of `data.frames.observable_rows`.
  """
  rows = frames_lib.observable_rows(rec, frames)
  if section is not None:
    x = frames_lib.image_centre(rec, rows)[:, 0]
    rows = rows[(x >= section[0]) & (x <= section[1])]
  if len(rows) == 0:
    raise UserError(f"{rec.path}: no vehicle has 3 s of history at the chosen frames")
  block = predictor.scenarios_per_call  # one jitted call each: memory bounded by the samples of one
  start, cpu = time.perf_counter(), time.process_time()
  parts = [
      predict(
          predictor, obs_lib.from_recording(rec, rows[i : i + block]), seed=seed, samples=samples
      )
      for i in tqdm(
          range(0, len(rows), block), desc="predict", unit="chunk", disable=len(rows) <= block
      )
  ]
  preds = concatenate(parts)
  seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
  summary = {
      "predictions": len(preds),
      "vehicles": int(len(np.unique(preds.track_id))),
      "frames": int(len(np.unique(preds.frame))),
      "seconds": round(seconds, 3),
      "cpu_seconds": round(cpu, 3),
      "predictions_per_second": round(len(preds) / seconds, 2),
      "out_of_distribution": int(preds.out_of_distribution.sum()),
  }
  if every is not None and 0 < every < preds.means.shape[2]:
    change = temporal_consistency(preds, every)
    summary["consistency_m"] = {
        "pairs": len(change),
        "mean": float(change.mean()) if len(change) else None,
        "median": float(np.median(change)) if len(change) else None,
    }
  return preds, summary
