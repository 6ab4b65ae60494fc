"""The quality benchmark: the demo's trained models on large new SUMO test sets.

  .venv/bin/python experiments/benchmark_quality.py --workdir=runs/quality \\
      --runs=runs/demo,runs/demo_s1,runs/demo_s2        # or: make benchmark-quality

Builds once (cached in `<workdir>/data`) new recordings of the test roads (`--test_recordings`
of 240 s drawn from the test ranges of configs/dataset.py with SUMO seed `--sumo_seed`, not
the demo's 0) and of the held-out road (`--ood_recordings` of 100 s): >= 1,000 scenarios per
class on each. Then, per trained run (a `make demo` directory with data/, tokenizer/, the
`--denoiser` run, baseline/ and, where present, mdn/), scores every model
(`evaluation.predictive`) with the same proper scores (`evaluation.model_scores`):
settings (kernel rules: `evaluation.regions`) chosen on the run's own val split,
scored on the new test and test_ood sets and on the run's val_ood. Writes
`<workdir>/quality.md` (tables with vehicle-bootstrap intervals; split-conformal and online
regions),
`quality.json`, `scores_<run>_<split>.npz` (every model's per-scenario scores, written as
each run is scored; `--reuse` takes them instead of scoring that run again),
`bandwidths_<run>.json` and `region_reliability_<split>.png`. Regions are calibrated on new
validation recordings (`--val_recordings` of the val ranges and `--val_ood_recordings` of
the val_ood road, SUMO seed `--cal_sumo_seed`, cached in `<workdir>/cal_data`, class-balanced
subsets of `--max_calibration` each), pooled; densities are chosen on the run's own val.
cVMDx's predictions are cached in `<workdir>/predictions/<run>_<key>.npz`, the key a hash of
the model (checkpoints and sampling settings), the scenarios' inputs and the seed: a later
call (another density, more runs) reuses them, a retrained run or other settings do not.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import json
import time
from pathlib import Path

import numpy as np
from absl import app, flags

from configs import dataset as dataset_config
from configs import distill as distill_config
from cvmdx_jax.data import dataset
from cvmdx_jax.data.scenarios import balanced_indices
from cvmdx_jax.evaluation import (
    figures,
    learned_baseline,
    prediction_cache,
    prob_calibration,
    quality,
    quality_tables,
    regions,
)
from cvmdx_jax.inference import mdn_baseline
from cvmdx_jax.inference.bundles import load_baseline
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.storage import atomic, checksums

_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory (dataset cached inside).")
_RUNS = flags.DEFINE_list("runs", None, "Trained demo directories (one per training seed).")
_DENOISER = flags.DEFINE_string(
    "denoiser",
    f"student_progressive_{distill_config.STUDENTS[-1]}",
    "The denoiser run inside each demo directory (default: the demo's last student).",
)
_TEST = flags.DEFINE_integer(
    "test_recordings", 4, "New test-road recordings of 240 s.", lower_bound=1
)
_OOD = flags.DEFINE_integer(
    "ood_recordings", 3, "New held-out-road recordings of 100 s.", lower_bound=1
)
_DURATION = flags.DEFINE_float(
    "duration_s", 240.0, "Seconds per test-road recording.", lower_bound=60.0
)
_SUMO_SEED = flags.DEFINE_integer(
    "sumo_seed", 101, "SUMO seed of the new recordings.", lower_bound=1
)
_MAX = flags.DEFINE_integer(
    "max_scenarios", 0, "Class-balanced subset per split (0 = all).", lower_bound=0
)
_CAL_SEED = flags.DEFINE_integer(
    "cal_sumo_seed", 102, "SUMO seed of the new calibration recordings.", lower_bound=1
)
_VAL = flags.DEFINE_integer(
    "val_recordings", 4, "New val-range calibration recordings of 240 s.", lower_bound=1
)
_VAL_OOD = flags.DEFINE_integer(
    "val_ood_recordings", 2, "New val_ood-road calibration recordings.", lower_bound=1
)
_MAX_CAL = flags.DEFINE_integer(
    "max_calibration", 600, "Class-balanced subset of each calibration split.", lower_bound=3
)
_SEED = flags.DEFINE_integer("seed", 0, "Sampling, Monte Carlo and bootstrap seed.", lower_bound=0)
_TEMPERATURE = flags.DEFINE_float(
    "prob_temperature",
    None,
    "p(c) temperature of every run's hypotheses instead of the run's own "
    "(experiments/calibrate_probs.py chooses one on val).",
    lower_bound=1e-3,
)
_REUSE = flags.DEFINE_bool(
    "reuse",
    False,
    "Take a run's scores from an earlier call's "
    "scores_<run>_<split>.npz in --workdir instead of scoring it again "
    "(runs are told apart by their directory name).",
)
flags.mark_flags_as_required(["workdir", "runs"])
cli.output_dirs("workdir")

SCORED = ("test", "test_ood", "val_ood")


def _new_recordings(data_dir: Path, seed: int, counts: dict) -> dict:
  """Builds (once) new SUMO recordings of the default config: {split: count}."""
  config = dataset_config.get_config()
  config.sumo.seed = seed
  config.sumo.duration_s = _DURATION.value
  config.sumo.recordings.update(
      {"train": 0, "val": 0, "val_ood": 0, "test": 0, "test_ood": 0, **counts}
  )
  return dataset.build(config, data_dir)


def _subset(scenarios, size: int):
  if not size or len(scenarios) <= size:
    return scenarios
  return scenarios.take(balanced_indices(scenarios.label, _SEED.value, size))


def _score_run(run: Path, large: dict, calibration, workdir: Path, log):
  predictor = Predictor.load(run / "tokenizer", run / _DENOISER.value)
  if _TEMPERATURE.value is not None:
    predictor = prob_calibration.with_temperature(predictor, _TEMPERATURE.value)
  predict = prediction_cache.cached(
      predictor, workdir / "predictions", run.name, prediction_cache.model_id(predictor)
  )
  baseline = None
  if (run / "baseline").is_dir():
    baseline = load_baseline(run / "baseline")
    learned_baseline.check_tokenizer(baseline, predictor.tokenizer, str(run / "baseline"))
  mdn_fn = None
  if (run / "mdn").is_dir():
    mdn = mdn_baseline.load_mdn(run / "mdn")
    learned_baseline.check_tokenizer(mdn, predictor.tokenizer, str(run / "mdn"))
    mdn_fn = lambda out, s: mdn(out.q, out.delta, s.xi, s.mask, s.v0, s.psi0)
  splits = {
      "test": _subset(large["test"], _MAX.value),
      "test_ood": _subset(large["test_ood"], _MAX.value),
      "val_ood": _subset(dataset.load_split(run / "data", "val_ood"), _MAX.value),
  }
  val = _subset(dataset.load_split(run / "data", "val"), _MAX.value)
  return quality.evaluate_run(
      predict, baseline, mdn_fn, val, splits, calibration, seed=_SEED.value, log=log
  )


def _save_run(workdir: Path, name: str, scores: quality.RunScores) -> None:
  """`scores_<name>_<split>.npz` (meta + `<model>__<score>` per scenario) and
  `bandwidths_<name>.json`, written as soon as a run is scored."""
  files = {workdir / f"bandwidths_{name}.json": atomic.json_text(scores.bandwidths).encode()}
  for split, data in scores.splits.items():
    arrays = {
        **data["meta"],
        **{f"{m}__{k}": v for m, row in data.items() if m != "meta" for k, v in row.items()},
    }
    files[workdir / f"scores_{name}_{split}.npz"] = checksums.npz_bytes(**arrays)
  checksums.write_all(files)


def _load_run(workdir: Path, name: str) -> quality.RunScores | None:
  """A run's saved scores (`_save_run`), or None where a file is missing."""
  paths = [workdir / f"scores_{name}_{split}.npz" for split in SCORED]
  if not all(p.is_file() for p in paths) or not (workdir / f"bandwidths_{name}.json").is_file():
    return None
  splits = {}
  for split, path in zip(SCORED, paths):
    with np.load(path) as z:
      data = {"meta": {k: z[k] for k in z.files if "__" not in k}}
      for key in (k for k in z.files if "__" in k):
        model, score = key.split("__")
        data.setdefault(model, {})[score] = z[key]
    splits[split] = data
  bandwidths = json.loads((workdir / f"bandwidths_{name}.json").read_text())
  return quality.RunScores(bandwidths=bandwidths, levels={}, splits=splits)


def _files(workdir: Path, runs: dict, build_s: float, seconds: dict) -> dict:
  doc = {"build_s": build_s, "seconds": seconds, "splits": {}}
  md = ["# Quality benchmark", ""]
  for split in SCORED:
    table = quality_tables.summary(runs, split)
    diffs = quality_tables.differences(runs, split)
    doc["splits"][split] = {"summary": table, "differences": diffs}
    md += [
        f"## {split}",
        "",
        quality_tables.summary_table(table),
        quality_tables.difference_table(diffs),
    ]
  md += [
      "## Calibrated 90 % regions",
      "",
      quality_tables.calibration_table(runs, SCORED),
      "Per recording, cVMDx's samples (a recording's traffic and drivers are shared by its "
      "scenarios; experiments/region_groups.py checks groupings across recordings):",
      "",
      quality_tables.recording_table(runs, SCORED),
      "## Online 90 % regions (adaptive conformal, truths as they arrive)",
      "",
      quality_tables.online_table(runs, SCORED),
      "## Hypothesis sets of p(c) at 0.9",
      "",
      quality_tables.hypothesis_set_table(runs, SCORED),
  ]
  doc["bandwidths"] = {name: r.bandwidths for name, r in runs.items()}
  files = {
      workdir / "quality.json": atomic.json_text(doc).encode(),
      workdir / "quality.md": "\n".join(md).encode(),
  }
  first = next(iter(runs.values()))
  for split in SCORED:
    u = {
        m: {s: row[f"hdr_u_{s}s"] for s in regions.HORIZONS_S}
        for m, row in first.splits[split].items()
        if m != "meta"
    }
    files[workdir / f"region_reliability_{split}.png"] = figures.plot_region_reliability(
        u, regions.HORIZONS_S, f"{next(iter(runs))}, {split}"
    )
  return files


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  workdir = Path(_WORKDIR.value)
  runs = [Path(r) for r in _RUNS.value]
  for run in runs:
    for part in ("tokenizer", _DENOISER.value, "data"):
      if not (run / part).is_dir():
        raise app.UsageError(f"--runs: {run / part} is not a directory (a make demo run?)")
  start = time.time()
  large = _new_recordings(
      workdir / "data", _SUMO_SEED.value, {"test": _TEST.value, "test_ood": _OOD.value}
  )
  cal = _new_recordings(
      workdir / "cal_data", _CAL_SEED.value, {"val": _VAL.value, "val_ood": _VAL_OOD.value}
  )
  calibration = [_subset(cal[k], _MAX_CAL.value) for k in ("val", "val_ood")]
  build_s = round(time.time() - start, 1)
  print(
      f"test sets: {', '.join(f'{k} {len(v)}' for k, v in large.items())} ({build_s} s)", flush=True
  )
  scored, seconds = {}, {}
  for run in runs:
    start = time.time()
    scored[run.name] = _load_run(workdir, run.name) if _REUSE.value else None
    if scored[run.name] is None:
      print(f"scoring {run}", flush=True)
      scored[run.name] = _score_run(
          run, large, calibration, workdir, lambda m: print(m, flush=True)
      )
      _save_run(workdir, run.name, scored[run.name])
    seconds[run.name] = round(time.time() - start, 1)
  checksums.write_all(_files(workdir, scored, build_s, seconds))
  print((workdir / "quality.md").read_text())
  print(json.dumps({"build_s": build_s, "seconds": seconds}))


if __name__ == "__main__":
  cli.run(main)
