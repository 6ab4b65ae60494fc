"""One evaluation run: predictions on a split, baselines, metrics.json, tables, figures.

Writes into `workdir`: `metrics<suffix>.json` ({method: {subset: {metric: value}}},
methods `scoring.METHODS` (and, given a trained baseline, `learned_baseline.METHODS`),
subsets all / kl / lcr / lcl, metrics in `scoring`'s
docstring, plus `_meta`), `results<suffix>.md` (the tables),
`predictions_<class><suffix>.png` (Fig. 1 style, for the classes present),
`kl_vs_usage<suffix>.png` (Fig. 3 style), `reliability<suffix>.png` (calibration of
the hypothesis probabilities) and `predictions<suffix>.npz`
(`files.prediction_arrays`: each scenario's provenance, mean, hypotheses with
probabilities and every method's per-scenario scores, for paired comparisons with
baselines of one's own). The markdown ends with the paired comparisons of cVMDx against
every baseline (`comparisons`: differences with 95 % vehicle-bootstrap intervals).

`run` = `report_models.load` (the runs, once) + `evaluate` (-> `files.Report`, plain
data, nothing written) + `files.write`. Every input is checked before anything is written,
non-finite predictions stop the run (`scoring.NonFinitePredictionError`) before anything
is written, and the report is written as a whole or not at all: every file is rendered in
memory, then written as one group (`checksums.write_all`), so a failure (a full disk)
leaves the previous report of this suffix, or none, and no temporary; a class figure of
the previous report that this one lacks is removed.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.data.scenarios import balanced_indices
from cvmdx_jax.evaluation import (
    comparisons,
    figures,
    learned_baseline,
    mdn_rows,
    report_models,
    score_tables,
    scoring,
)
from cvmdx_jax.evaluation import report_files as files
from cvmdx_jax.evaluation import token_kl as kl
from cvmdx_jax.runs import memory
from cvmdx_jax.storage import locking


def _errors(models: report_models.Models, out, scenarios) -> dict:
  """Per-scenario errors of every method (`scoring`, `learned_baseline`, `mdn_rows`)."""
  gt = jnp.asarray(scenarios.future)
  errors = {**scoring.cvmdx_errors(out, gt, scenarios.label), **scoring.baseline_errors(scenarios)}
  if models.baseline is not None:
    errors.update(learned_baseline.scenario_errors(models.baseline, out.q, out.delta, scenarios))
  if models.mdn is not None:
    mixture = models.mdn(
        out.q, out.delta, scenarios.xi, scenarios.mask, scenarios.v0, scenarios.psi0
    )
    errors.update(mdn_rows.errors(mixture, gt, scenarios.label))
  return errors


def _ddpm_results(
    models: report_models.Models, scenarios, seed: int, size: int, split: str
) -> dict:
  """The single-DDPM-sample row on a class-balanced subset of `size` ({} if none)."""
  if not size:
    return {}
  if models.ddpm is None:
    print(
        f"note: {models.dirs['ddpm_diffusion_dir'] or models.dirs['diffusion_dir']} is a "
        "progressive student (it knows only its own steps): no single-DDPM row; pass the "
        "guided denoiser as the DDPM run",
        flush=True,
    )
    return {}
  sub = scenarios.take(balanced_indices(scenarios.label, seed, size))
  single = dataclasses.replace(
      models.ddpm.sampling,
      sampler="ddpm",
      num_samples=1,
      hypotheses=HypothesisConfig(c_max=1, pca_dim=1),
  )
  ddpm = dataclasses.replace(models.ddpm, sampling=single)(sub, seed=seed)
  scoring.check_finite(ddpm.prediction, sub, f"single DDPM sample on split {split}")
  return scoring.summarise(
      {"ddpm_single": scoring.single_trajectory_errors(ddpm.mean, jnp.asarray(sub.future))},
      sub.label,
  )


def _figures(models: report_models.Models, scenarios, out, diagram, split: str, per_class: int):
  """({stem: PNG bytes}, stale class-figure stems, KL power-law fit)."""
  token_kl = kl.kl_per_token(out.q, scenarios.future, out.prediction.trajectories, models.usage)
  q_count = len(models.usage)
  kl_png, fit = figures.plot_kl_vs_usage(token_kl, f"Q = {q_count}, split {split}")
  pngs = {
      "kl_vs_usage": kl_png,
      "reliability": figures.plot_reliability(
          diagram, f"{models.predictor.sampling.hypotheses.method}, split {split}"
      ),
  }
  stale = []
  for c, name in enumerate(constants.CLASS_NAMES):
    idx = np.flatnonzero(scenarios.label == c)[:per_class]
    if len(idx):
      pngs[f"predictions_{name}"] = figures.plot_predictions(scenarios, out, idx)
    else:
      stale.append(f"predictions_{name}")
  return pngs, tuple(stale), fit


def evaluate(
    models: report_models.Models,
    scenarios,
    *,
    split: str,
    seed: int = 0,
    ddpm_scenarios: int = 300,
    figures_per_class: int = 3,
    data_dir=None,
) -> files.Report:
  """Evaluates `models` on `scenarios` (split `split` of the dataset in `data_dir`); nothing
  is written. Raises `scoring.NonFinitePredictionError` on non-finite predictions."""
  predictor = models.predictor
  out = predictor(scenarios, seed=seed)
  scoring.check_finite(out.prediction, scenarios, f"cVMDx on split {split}")
  errors = _errors(models, out, scenarios)
  results = scoring.summarise(errors, scenarios.label)
  for subset, row in scoring.delta_rank_correlation(
      out.delta, errors["cvmdx_mean"]["ade"], scenarios.label
  ).items():
    results["cvmdx_mean"][subset].update(row)
  hyp = out.hypotheses
  ece, diagram = scoring.calibration(
      hyp.means, hyp.probs, jnp.asarray(scenarios.future), scenarios.label
  )
  for subset, row in ece.items():
    results["cvmdx_best_of_k"][subset].update(row)
  results.update(_ddpm_results(models, scenarios, seed, ddpm_scenarios, split))
  pngs, stale, fit = _figures(models, scenarios, out, diagram, split, figures_per_class)
  differences = comparisons.paired(
      errors, scenarios.recording_id, scenarios.track_id, scenarios.label, seed=seed
  )
  meta = {
      "split": split,
      "num_scenarios": len(scenarios),
      "seed": seed,
      "sampling": report_models.sampling_meta(predictor),
      **{k: v for k, v in models.dirs.items() if v is not None and k != "baseline_dir"},
      "data_dir": str(data_dir),
      "dataset_id": None if data_dir is None else dataset_lib.dataset_id(data_dir),
      "baseline": None
      if models.baseline is None
      else {"dir": models.dirs["baseline_dir"], "epoch": models.baseline.epoch},
      "checkpoints": models.checkpoints,
      "kl_power_law_fit": fit,
      "reliability": diagram,
      "tokens_in_use_on_split": int(len(np.unique(out.q))),
      "out_of_distribution": {
          "rule": "delta > delta_limit, the largest delta over the tokeniser's train split",
          "delta_limit": predictor.delta_limit,
          "count": int(out.out_of_distribution.sum()),
          "share": float(out.out_of_distribution.mean()),
      },
      "comparisons": differences,
  }
  tables = score_tables.markdown_tables(results) + "\n" + comparisons.markdown(differences)
  return files.Report(
      results, meta, tables, files.prediction_arrays(scenarios, out, errors), pngs, stale
  )


@locking.holds("workdir")
def run(
    *,
    tokenizer_dir,
    diffusion_dir,
    data_dir,
    workdir,
    split: str = "test",
    seed: int = 0,
    max_scenarios: int = 0,
    ddpm_scenarios: int = 300,
    figures_per_class: int = 3,
    sampling_overrides=None,
    suffix: str = "",
    baseline_dir=None,
    ddpm_diffusion_dir=None,
    mdn_dir=None,
) -> dict:
  """Evaluates a trained cVMDx on `split` of the dataset in `data_dir` and writes the report.

  Args:
    tokenizer_dir, diffusion_dir: the two training runs.
    data_dir: dataset folder (`cvmdx_jax.data.dataset`).
    workdir: where the report goes (created).
    split: split name; an unknown one raises before anything is written.
    seed: sampling seed.
    max_scenarios: evaluate a class-balanced subset of this size (0 = all).
    ddpm_scenarios: scenarios of the (100x slower) single-DDPM-sample baseline, a
      class-balanced subset of the evaluated ones (0 = skip it).
    ddpm_diffusion_dir: the run whose denoiser draws that baseline (None: `diffusion_dir`).
      A progressive student knows only its own steps: with one and no other run the row is
      left out (a printed note); give the guided denoiser it was distilled from.
    figures_per_class: scenarios drawn per class in the prediction figures.
    sampling_overrides: `SamplingConfig` fields set instead of the diffusion run's
      (e.g. {"sampler": "ddim", "steps": 10}), and "prob_temperature" for the hypotheses'
      `HypothesisConfig.prob_temperature`.
    suffix: appended to every file name (`metrics<suffix>.json`, ...), so that several
      splits can be reported into one directory.
    baseline_dir: a trained multiple-choice baseline (`cvmdx_jax.train.baseline`) whose
      rows (`learned_baseline.METHODS`) join the report; it must have been trained on
      this tokeniser's tokens (`learned_baseline.IncompatibleBaselineError`). None: no rows.
    mdn_dir: a trained mixture density network (`cvmdx_jax.train.mdn`) whose rows
      (`mdn_rows.METHODS`) join the report, on this tokeniser's tokens. None: no rows.

  Returns:
    The metrics dict written to metrics.json.
  """
  scenarios = dataset_lib.load_balanced(data_dir, split, seed, max_scenarios)
  models = report_models.load(
      tokenizer_dir=tokenizer_dir,
      diffusion_dir=diffusion_dir,
      sampling_overrides=sampling_overrides,
      baseline_dir=baseline_dir,
      ddpm_diffusion_dir=ddpm_diffusion_dir,
      mdn_dir=mdn_dir,
  )
  report = evaluate(
      models,
      scenarios,
      split=split,
      seed=seed,
      ddpm_scenarios=ddpm_scenarios,
      figures_per_class=figures_per_class,
      data_dir=data_dir,
  )
  files.write(report, workdir, suffix)
  return report.results


def split_suffix(split: str) -> str:
  """The file-name suffix of `split` in `run_test_and_ood`'s directory: "" for test
  (metrics.json), "_<split>" otherwise (metrics_test_ood.json)."""
  return "" if split == "test" else f"_{split}"


@locking.holds("workdir")
def run_test_and_ood(
    *,
    tokenizer_dir,
    diffusion_dir,
    data_dir,
    workdir,
    ddpm_scenarios: int,
    ood_ddpm_scenarios: int,
    seed: int = 0,
    max_scenarios: int = 0,
    baseline_dir=None,
    ddpm_diffusion_dir=None,
    mdn_dir=None,
) -> dict:
  """Reports on test (metrics.json, results.md, ...) and, where the dataset has the split,
  on test_ood (metrics_test_ood.json, results_test_ood.md, ...) into one `workdir`, in
  the same schema; without test_ood a note is printed. Arguments as in `run`, with
  `ood_ddpm_scenarios` the DDPM baseline's subset on test_ood; the runs are loaded once,
  and after each split `memory.release` hands back what it compiled and freed (JAX's caches
  included). Returns {split: metrics}."""
  splits = {"test": ddpm_scenarios}
  if "test_ood" in dataset_lib.split_names(data_dir):
    splits["test_ood"] = ood_ddpm_scenarios
  else:
    print(
        f"note: {data_dir} has no test_ood split (the highD and cvmd_mat sources have "
        "none); only the test split is evaluated",
        flush=True,
    )
  loaded = {
      split: dataset_lib.load_balanced(data_dir, split, seed, max_scenarios) for split in splits
  }
  models = report_models.load(
      tokenizer_dir=tokenizer_dir,
      diffusion_dir=diffusion_dir,
      baseline_dir=baseline_dir,
      ddpm_diffusion_dir=ddpm_diffusion_dir,
      mdn_dir=mdn_dir,
  )
  out = {}
  for split, ddpm in splits.items():
    report = evaluate(
        models, loaded[split], split=split, seed=seed, ddpm_scenarios=ddpm, data_dir=data_dir
    )
    files.write(report, workdir, split_suffix(split))
    out[split] = report.results
    del report
    # the scores' many small programs and the freed pages of one split are not kept for the
    # next: the process's peak is one split's, not their sum (1.8 GB against 2.4-2.8 GB
    # in the demo, docs/log/2026-12-06-one-step-default.md)
    memory.release()
  return out
