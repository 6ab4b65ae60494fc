"""Which covariate of t0 to group cVMDx's calibrated 90 % regions by, checked across recordings.

  .venv/bin/python experiments/region_groups.py --run=runs/demo \\
      --data_dir=runs/quality/cal_data --workdir=runs/region_groups

Chooses the samples' density on the run's own val (as `benchmark_quality.py`), then on the
recordings of `--data_dir` (give validation recordings: the quality benchmark's cal_data)
leaves each recording out in turn: levels calibrated on the others (plain, or per tercile of
each covariate of `evaluation.region_groups`), the left-out recording's coverage at 1..5 s.
Prints and writes `<workdir>/region_groups.md` and `.json`: per candidate the mean and the
largest |coverage - 0.9| over recordings and seconds, and each recording's coverage. A
grouping carries to a road no calibration recording has only where it lowers both.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

from pathlib import Path

import jax
import numpy as np
from absl import app, flags

from configs import distill as distill_config
from cvmdx_jax.data import dataset
from cvmdx_jax.evaluation import (
    model_scores,
    prediction_cache,
    predictive,
    quality,
    region_groups,
    regions,
)
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.storage import atomic, checksums

_RUN = flags.DEFINE_string("run", None, "A trained demo directory (data/, tokenizer/, denoiser).")
_DENOISER = flags.DEFINE_string(
    "denoiser",
    f"student_progressive_{distill_config.STUDENTS[-1]}",
    "The denoiser run inside --run.",
)
_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory of the calibration recordings.")
_SPLITS = flags.DEFINE_list("splits", ["val", "val_ood"], "Its splits, pooled.")
_MAX = flags.DEFINE_integer(
    "max_scenarios", 600, "Class-balanced subset of each split (0 = all).", lower_bound=0
)
_SEED = flags.DEFINE_integer("seed", 0, "Sampling and Monte Carlo seed.", lower_bound=0)
_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory (predictions cached inside).")
flags.mark_flags_as_required(["run", "data_dir", "workdir"])
cli.input_dirs("run", "data_dir")
cli.output_dirs("workdir")


def _scores(predict, bandwidths, scenarios):
  """(M, H) u of the truths, the covariates (M,) each, recording ids (M,)."""
  out = predict(scenarios, seed=_SEED.value)
  model = predictive.cvmdx_models(out)[0]
  key = jax.random.fold_in(jax.random.key(_SEED.value), 1)
  u = quality.conformity_scores(model, bandwidths, np.asarray(scenarios.future, np.float32), key)
  return u, region_groups.covariates(scenarios, out), np.asarray(scenarios.recording_id)


def table(u, covariates: dict, recordings) -> list[dict]:
  """Per candidate (plain, then each covariate): errors and each recording's coverage."""
  rows = []
  for name in ("plain", *region_groups.COVARIATES):
    ids, counts, cover = region_groups.leave_one_out(u, recordings, covariates.get(name))
    mean, largest = region_groups.errors(counts, cover)
    rows.append(
        {
            "candidate": name,
            "mean_error": mean,
            "largest_error": largest,
            "recordings": [
                {"id": int(i), "scenarios": int(n), "coverage": c.tolist()}
                for i, n, c in zip(ids, counts, cover)
            ],
        }
    )
  return rows


def markdown(rows) -> str:
  seconds = " | ".join(f"{s} s" for s in regions.HORIZONS_S)
  lines = [
      "| grouping | mean abs(coverage - 0.9) | largest |",
      "|---|---|---|",
      *(f"| {r['candidate']} | {r['mean_error']:.4f} | {r['largest_error']:.4f} |" for r in rows),
      "",
      f"| grouping | recording | scenarios | {seconds} |",
      "|---|---|---|" + "---|" * len(regions.HORIZONS_S),
  ]
  for r in rows:
    for rec in r["recordings"]:
      cells = " | ".join(f"{c:.3f}" for c in rec["coverage"])
      lines.append(f"| {r['candidate']} | {rec['id']} | {rec['scenarios']} | {cells} |")
  return "\n".join(lines) + "\n"


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  run, workdir = Path(_RUN.value), Path(_WORKDIR.value)
  for part in ("tokenizer", _DENOISER.value, "data"):
    if not (run / part).is_dir():
      raise app.UsageError(f"--run: {run / part} is not a directory (a make demo run?)")
  sets = [dataset.load_balanced(_DATA.value, s, _SEED.value, _MAX.value) for s in _SPLITS.value]
  held = np.unique(np.concatenate([np.asarray(s.recording_id) for s in sets]))
  if len(held) < 2:
    raise app.UsageError(
        f"--data_dir / --splits: {len(held)} recording(s) in {_DATA.value} "
        f"{','.join(_SPLITS.value)}; leaving one out needs 2 or more"
    )
  predictor = Predictor.load(run / "tokenizer", run / _DENOISER.value)
  predict = prediction_cache.cached(
      predictor, workdir / "predictions", run.name, prediction_cache.model_id(predictor)
  )
  val = dataset.load_split(run / "data", "val")
  val_model = predictive.cvmdx_models(predict(val, seed=_SEED.value))[0]
  bandwidths = model_scores.choose_bandwidths(val_model, np.asarray(val.future, np.float32))
  found = [_scores(predict, bandwidths, s) for s in sets]
  u = np.concatenate([f[0] for f in found])
  covariates = {k: np.concatenate([f[1][k] for f in found]) for k in found[0][1]}
  recordings = np.concatenate([f[2] for f in found])
  rows = table(u, covariates, recordings)
  text = markdown(rows)
  checksums.write_all(
      {
          workdir / "region_groups.json": atomic.json_text({"rows": rows}).encode(),
          workdir / "region_groups.md": text.encode(),
      }
  )
  print(text)


if __name__ == "__main__":
  cli.run(main)
