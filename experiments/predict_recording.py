"""Predicts every vehicle of a highD-format recording at every k-th frame.

  .venv/bin/python experiments/predict_recording.py --tokenizer_dir=runs/demo/tokenizer \\
      --diffusion_dir=runs/demo/student_progressive_1 \\
      --recording=runs/demo/data/recordings/17_tracks.csv --every=5 \\
      --out=runs/demo/predictions_17.csv.gz [--start=10s --end=20s] [--samples] \\
      [--animation=runs/demo/scene_17.gif] [--host_devices=2]

The recording is `--recording=<dir>/NN_tracks.csv` or `--highd_dir=<dir> --recording_id=NN`
(highD and the project's SUMO recordings alike). Every vehicle with 3 s of history at a
frame of the window is predicted (batched over vehicles and frames). `--out` gets the
tidy table (`inference.recording.TABLE_COLUMNS`: recording, frame, track_id, kind,
hypothesis, probability, t, x, y; x, y the bounding-box centre in the recording's image
frame, as tracks.csv, so it overlays highD's background image), as Parquet (.parquet,
needs pyarrow) or gzip-compressed CSV (.csv.gz); `<out>.provenance.json` the runs'
fingerprints, settings, input checksums, code version and the summary printed at the end
(predictions per second, temporal consistency, accuracy where the recording holds the
5 s after t0).
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import re
import subprocess
from pathlib import Path

import numpy as np
from absl import app, flags

import cvmdx_jax
from cvmdx_jax import constants, sharding
from cvmdx_jax.data import frames as frames_lib
from cvmdx_jax.data import highd
from cvmdx_jax.errors import UserError
from cvmdx_jax.evaluation import metrics
from cvmdx_jax.inference import recording
from cvmdx_jax.inference.predictor import SAMPLES_PER_CALL, SCENARIOS_PER_CALL, Predictor
from cvmdx_jax.storage import atomic, checksums, identity

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion (or student) run directory.")
_RECORDING = flags.DEFINE_string("recording", None, "A recording's <dir>/NN_tracks.csv.")
_HIGHD = flags.DEFINE_string(
    "highd_dir",
    None,
    "Directory of highD-format recordings " "(with --recording_id, instead of --recording).",
)
_RECORDING_ID = flags.DEFINE_integer(
    "recording_id", None, "Recording NN in --highd_dir.", lower_bound=0
)
_EVERY = flags.DEFINE_integer("every", 5, "Predict at every k-th frame.", lower_bound=1)
_START = flags.DEFINE_string(
    "start",
    None,
    "First frame of the window: a frame number, or "
    "seconds from the recording's first frame with an 's' (10s).",
)
_END = flags.DEFINE_string("end", None, "Last frame of the window (as --start).")
_OUT = flags.DEFINE_string("out", None, "The table: <file>.parquet or <file>.csv.gz.")
_SAMPLES = flags.DEFINE_bool("samples", False, "Also write every sampled trajectory.")
_NUM_SAMPLES = flags.DEFINE_integer(
    "num_samples", None, "Samples per vehicle instead of the " "run's.", lower_bound=1
)
_SEED = flags.DEFINE_integer("seed", 0, "Sampling seed.", lower_bound=0, upper_bound=2**32 - 1)
_CHUNK = flags.DEFINE_integer(
    "chunk_size",
    None,
    f"Vehicle-frames per jitted call (default: {SCENARIOS_PER_CALL}, fewer where "
    f"their samples would exceed {SAMPLES_PER_CALL:,} trajectories a call).",
    lower_bound=1,
)
_HOST_DEVICES = flags.DEFINE_integer(
    "host_devices",
    1,
    "CPU devices to split each call's vehicles over (`sharding.use_host_devices`): one per "
    "core is faster on CPU (docs/benchmarks.md); outputs equal 1's to float rounding.",
    lower_bound=1,
)
_ANIMATION = flags.DEFINE_string("animation", None, "Also write a GIF of the window.")
_SECTION = flags.DEFINE_list(
    "animation_x",
    None,
    "x0,x1: the section of the road the GIF " "shows (image x, m; default the whole road).",
)
flags.mark_flags_as_required(["tokenizer_dir", "diffusion_dir", "out"])
cli.input_dirs("tokenizer_dir", "diffusion_dir", "highd_dir")


def _source() -> tuple[Path, int]:
  """(directory, recording id) from --recording or --highd_dir / --recording_id."""
  if (_RECORDING.value is None) == (_HIGHD.value is None):
    raise UserError(
        "give either --recording=<dir>/NN_tracks.csv or --highd_dir with " "--recording_id"
    )
  if _RECORDING.value is not None:
    path = Path(_RECORDING.value)
    match = re.fullmatch(r"([0-9]+)_tracks\.csv", path.name)
    if match is None:
      raise UserError(f"--recording={path}: expected a file named NN_tracks.csv")
    if not path.is_file():
      raise UserError(f"--recording={path}: file not found")
    return path.parent, int(match.group(1))
  if _RECORDING_ID.value is None:
    raise UserError("--highd_dir needs --recording_id")
  return Path(_HIGHD.value), _RECORDING_ID.value


def _frame(flag, value: str | None, first: int, last: int, default: int) -> int:
  """A --start / --end value as a frame of the recording (`first`..`last`)."""
  if value is None:
    return default
  try:
    frame = (
        first + round(float(value[:-1]) * constants.FRAME_RATE_HZ)
        if value.endswith("s")
        else int(value)
    )
  except ValueError as err:
    raise UserError(f"--{flag}={value}: expected a frame number or seconds like 10s") from err
  if not first <= frame <= last:
    raise UserError(
        f"--{flag}={value}: frame {frame} outside the recording (frames " f"{first}..{last})"
    )
  return frame


def _accuracy(preds, rec, frames) -> dict:
  """ADE / FDE (m) of the samples' mean and minADE / minFDE over the hypotheses,
  over the predictions whose 5 s after t0 the recording holds."""
  future, known = frames_lib.futures(rec, frames_lib.observable_rows(rec, frames))
  if not known.any():
    return {"count": 0}
  gt, hyps, valid = future[known], preds.means[known], preds.probs[known] > 0
  mean = preds.mean[known]
  values = {
      "ade": metrics.ade(mean, gt),
      "fde": metrics.fde(mean, gt),
      "min_ade": metrics.min_ade_k(hyps, gt, valid),
      "min_fde": metrics.min_fde_k(hyps, gt, valid),
  }
  return {"count": int(known.sum()), **{k: round(float(np.mean(v)), 4) for k, v in values.items()}}


def _section() -> tuple[float, float] | None:
  """--animation_x as (x0, x1), x0 < x1."""
  if _SECTION.value is None:
    return None
  try:
    x0, x1 = (float(x) for x in _SECTION.value)
  except ValueError as err:
    raise UserError(
        f"--animation_x={','.join(_SECTION.value)}: expected two numbers " "x0,x1"
    ) from err
  if not x0 < x1:
    raise UserError(f"--animation_x={','.join(_SECTION.value)}: needs x0 < x1")
  return x0, x1


def _code_version() -> dict:
  try:
    commit = (
        subprocess.run(
            ["git", "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent,
            timeout=10,
        ).stdout.strip()
        or None
    )
  except OSError:
    commit = None
  return {"cvmdx_jax": cvmdx_jax.__version__, "git_commit": commit}


def _provenance(predictor, data_dir, recording_id, window, summary, out) -> dict:
  paths = highd.recording_paths(data_dir, recording_id)
  runs = {
      name: {
          "dir": str(path),
          "fingerprint_id": identity.content_id(identity.to_json(bundle.fingerprint.to_dict())),
      }
      for name, path, bundle in (
          ("tokenizer", _TOKENIZER.value, predictor.tokenizer),
          ("diffusion", _DIFFUSION.value, predictor.denoiser),
      )
  }
  runs["tokenizer"]["checkpoint"] = identity.to_json(predictor.tokenizer.checkpoint.to_dict())
  return {
      "recording": {
          "id": recording_id,
          "files": {
              kind: {"name": path.name, "sha256": checksums.file_sha256(path)}
              for kind, path in paths.items()
          },
      },
      "window": window,
      "seed": _SEED.value,
      "host_devices": _HOST_DEVICES.value,
      "samples": _SAMPLES.value,
      "sampling": identity.to_json(dataclasses.asdict(predictor.sampling)),
      "runs": runs,
      "code": _code_version(),
      "table": str(out),
      "summary": summary,
  }


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  sharding.use_host_devices(_HOST_DEVICES.value)
  recording.check_table_path(_OUT.value)
  section = _section()
  data_dir, recording_id = _source()
  rec = highd.read_recording(data_dir, recording_id)
  first, last = frames_lib.frame_range(rec)
  start = _frame("start", _START.value, first, last, first)
  end = _frame("end", _END.value, first, last, last)
  if end < start:
    raise UserError(f"--end={_END.value}: before --start={_START.value}")
  frames = list(range(start, end + 1, _EVERY.value))
  if len(frames_lib.observable_rows(rec, frames)) == 0:
    raise UserError(
        f"{rec.path}: no vehicle has 3 s of history in frames {start}..{end} " "(--start / --end)"
    )
  predictor = Predictor.load(_TOKENIZER.value, _DIFFUSION.value, chunk_size=_CHUNK.value)
  if _NUM_SAMPLES.value is not None:
    predictor = dataclasses.replace(
        predictor, sampling=dataclasses.replace(predictor.sampling, num_samples=_NUM_SAMPLES.value)
    )
  preds, summary = recording.predict_frames(
      predictor, rec, frames, seed=_SEED.value, samples=_SAMPLES.value, every=_EVERY.value
  )
  summary["accuracy"] = _accuracy(preds, rec, frames)
  table = recording.table(preds)
  recording.write_table(table, _OUT.value)
  if _ANIMATION.value:
    from cvmdx_jax.evaluation import animation  # matplotlib only where a GIF is asked for

    gif = animation.render_gif(
        rec,
        frames_lib.scene(data_dir, recording_id),
        frames,
        preds,
        fps=constants.FRAME_RATE_HZ / _EVERY.value,
        x_range=section,
    )
    atomic.write_bytes(_ANIMATION.value, gif)
  window = {"start": start, "end": end, "every": _EVERY.value}
  summary["table_rows"] = len(table)
  atomic.write_json(
      f"{_OUT.value}.provenance.json",
      _provenance(predictor, data_dir, recording_id, window, summary, _OUT.value),
      indent=1,
  )
  for key, value in summary.items():
    print(f"{key}: {value}")


if __name__ == "__main__":
  cli.run(main)
