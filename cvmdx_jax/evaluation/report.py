"""One evaluation run: predictions on a split, baselines, metrics.json, tables, figures.

Writes into `workdir`: `metrics<suffix>.json` ({method: {subset: {metric: value}}},
methods `scoring.METHODS` (and, given a trained baseline, `learned_baseline.METHODS`),
subsets all / kl / lcr / lcl, metrics in `scoring`'s
docstring, plus `_meta`), `results<suffix>.md` (the tables),
`predictions_<class><suffix>.png` (Fig. 1 style, for the classes present),
`kl_vs_usage<suffix>.png` (Fig. 3 style), `reliability<suffix>.png` (calibration of
the hypothesis probabilities) and `predictions<suffix>.npz` (`prediction_arrays`: each
scenario's provenance, mean, hypotheses with probabilities and per-method errors, for
paired comparisons with baselines of one's own). Every input is checked before anything is written,
non-finite predictions stop the run (`scoring.NonFinitePredictionError`) before anything
is written, and the report is written as a whole or not at all: every file is rendered in
memory, then written as one group (`checksums.write_all`), so a failure (a full disk)
leaves the previous report of this suffix, or none, and no temporary; a class figure of
the previous report that this one lacks is removed.
"""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.data.scenarios import balanced_indices
from cvmdx_jax.evaluation import figures, learned_baseline, scoring
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.runs import loaders
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage import atomic, checksums, locking


def _sampling_meta(predictor: Predictor) -> dict:
  """The sampling settings of a report with the denoiser's control scale, conditioning and
  residual base among them (where metrics.json has always listed them)."""
  targets = predictor.denoiser.config.diffusion
  out = {}
  for name, value in dataclasses.asdict(predictor.sampling).items():
    out[name] = value
    if name == "clip_x0":
      out.update(control_scale=targets.control_scale, conditioning=targets.conditioning,
                 residual_decay_s=targets.residual_decay_s)
  return out


def prediction_arrays(scenarios, out, errors: dict) -> dict:
  """The arrays of `predictions<suffix>.npz`, one row per evaluated scenario (M):
  `recording_id`, `track_id`, `frame`, `label` (M,) int (the scenario's provenance, as in
  the dataset); `mean` (M, 125, 2) m; `hypotheses` (M, K, 125, 2) m and `probs` (M, K) (0 =
  unused slot); `q`, `delta`, `out_of_distribution` (M,); and `<method>_ade`,
  `<method>_fde` (M,) m for every method of `errors` (per-scenario errors on these M
  scenarios; best of K: minADE_K / minFDE_K)."""
  arrays = {name: np.asarray(getattr(scenarios, name))
            for name in ("recording_id", "track_id", "frame", "label")}
  arrays.update(mean=out.mean, hypotheses=out.hypotheses.means, probs=out.hypotheses.probs,
                q=out.q, delta=out.delta, out_of_distribution=out.out_of_distribution)
  for method, per in errors.items():
    arrays.update({f"{method}_{metric}": per[metric] for metric in ("ade", "fde")})
  return {name: np.asarray(value) for name, value in arrays.items()}


@locking.holds("workdir")
def run(*, tokenizer_dir, diffusion_dir, data_dir, workdir, split: str = "test",
        seed: int = 0, max_scenarios: int = 0, ddpm_scenarios: int = 300,
        figures_per_class: int = 3, sampling_overrides=None, suffix: str = "",
        baseline_dir=None, ddpm_diffusion_dir=None) -> dict:
  """Evaluates a trained cVMDx on `split` of the dataset in `data_dir`.

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
      (e.g. {"sampler": "ddim", "steps": 10}).
    suffix: appended to every file name (`metrics<suffix>.json`, ...), so that several
      splits can be reported into one directory.
    baseline_dir: a trained multiple-choice baseline (`cvmdx_jax.train.baseline`) whose
      rows (`learned_baseline.METHODS`) join the report; it must have been trained on
      this tokeniser's tokens (`learned_baseline.IncompatibleBaselineError`). None: no rows.

  Returns:
    The metrics dict written to metrics.json.
  """
  scenarios = dataset_lib.load_split(data_dir, split)
  predictor = Predictor.load(tokenizer_dir, diffusion_dir)
  if sampling_overrides:
    predictor = dataclasses.replace(predictor, sampling=dataclasses.replace(
        predictor.sampling, **sampling_overrides))
  if max_scenarios:
    scenarios = scenarios.take(balanced_indices(scenarios.label, seed, max_scenarios))
  usage_tokens, _ = tokens_lib.load_tokens(tokens_lib.tokens_path(tokenizer_dir, "train"))
  workdir = Path(workdir)
  baseline = None if baseline_dir is None else loaders.load_baseline(baseline_dir)
  if baseline is not None:
    learned_baseline.check_tokenizer(baseline, predictor.tokenizer, str(baseline_dir))

  out = predictor(scenarios, seed=seed)
  scoring.check_finite(out.prediction, scenarios, f"cVMDx on split {split}")
  gt = jnp.asarray(scenarios.future)
  errors = {**scoring.cvmdx_errors(out, gt, scenarios.label),
            **scoring.baseline_errors(scenarios)}
  if baseline is not None:
    errors.update(learned_baseline.scenario_errors(baseline, out.q, out.delta, scenarios))
  results = scoring.summarise(errors, scenarios.label)
  correlation = scoring.delta_rank_correlation(out.delta, errors["cvmdx_mean"]["ade"],
                                               scenarios.label)
  for subset, row in correlation.items():
    results["cvmdx_mean"][subset].update(row)
  hyp = out.hypotheses
  ece, diagram = scoring.calibration(hyp.means, hyp.probs, gt, scenarios.label)
  for subset, row in ece.items():
    results["cvmdx_best_of_k"][subset].update(row)
  ddpm_predictor = (predictor if ddpm_diffusion_dir is None
                    else Predictor.load(tokenizer_dir, ddpm_diffusion_dir))
  if ddpm_scenarios and ddpm_predictor.denoiser.progressive:
    print(f"note: {ddpm_diffusion_dir or diffusion_dir} is a progressive student (it knows only its own steps): no "
          "single-DDPM row; pass the guided denoiser as the DDPM run", flush=True)
  elif ddpm_scenarios:
    idx = balanced_indices(scenarios.label, seed, ddpm_scenarios)
    sub = scenarios.take(idx)
    single = dataclasses.replace(ddpm_predictor.sampling, sampler="ddpm", num_samples=1,
                                 hypotheses=HypothesisConfig(c_max=1, pca_dim=1))
    ddpm = dataclasses.replace(ddpm_predictor, sampling=single)(sub, seed=seed)
    scoring.check_finite(ddpm.prediction, sub, f"single DDPM sample on split {split}")
    results.update(scoring.summarise(
        {"ddpm_single": scoring.single_trajectory_errors(ddpm.mean, jnp.asarray(sub.future))},
        sub.label))
  workdir.mkdir(parents=True, exist_ok=True)

  q_count = predictor.tokenizer.config.quantizer.codebook_size
  usage = np.bincount(usage_tokens.q, minlength=q_count)
  token_kl = scoring.kl_per_token(out.q, scenarios.future, out.prediction.trajectories, usage)
  kl_png, fit = figures.plot_kl_vs_usage(token_kl, f"Q = {q_count}, split {split}")
  pngs = {workdir / f"kl_vs_usage{suffix}.png": kl_png,
          workdir / f"reliability{suffix}.png": figures.plot_reliability(
              diagram, f"{predictor.sampling.hypotheses.method}, split {split}")}
  stale = []
  for c, name in enumerate(constants.CLASS_NAMES):
    idx = np.flatnonzero(scenarios.label == c)[:figures_per_class]
    path = workdir / f"predictions_{name}{suffix}.png"
    if len(idx):
      pngs[path] = figures.plot_predictions(scenarios, out, idx)
    else:
      stale.append(path)

  meta = {"split": split, "num_scenarios": len(scenarios), "seed": seed,
          "sampling": _sampling_meta(predictor),
          "tokenizer_dir": str(tokenizer_dir), "diffusion_dir": str(diffusion_dir),
          **({} if ddpm_diffusion_dir is None
             else {"ddpm_diffusion_dir": str(ddpm_diffusion_dir)}),
          "data_dir": str(data_dir), "dataset_id": dataset_lib.dataset_id(data_dir),
          "baseline": None if baseline is None else {"dir": str(baseline_dir),
                                                     "epoch": baseline.epoch},
          "kl_power_law_fit": fit, "reliability": diagram,
          "tokens_in_use_on_split": int(len(np.unique(out.q))),
          "out_of_distribution": {
              "rule": "delta > delta_limit, the largest delta over the tokeniser's train split",
              "delta_limit": predictor.delta_limit,
              "count": int(out.out_of_distribution.sum()),
              "share": float(out.out_of_distribution.mean())}}
  checksums.write_all({  # metrics.json first: renamed last
      workdir / f"metrics{suffix}.json": atomic.json_text({**results, "_meta": meta}).encode(),
      workdir / f"results{suffix}.md": scoring.markdown_tables(results).encode(),
      workdir / f"predictions{suffix}.npz": checksums.npz_bytes(
          **prediction_arrays(scenarios, out, errors)), **pngs})
  for path in stale:
    path.unlink(missing_ok=True)
  return results


def split_suffix(split: str) -> str:
  """The file-name suffix of `split` in `run_test_and_ood`'s directory: "" for test
  (metrics.json), "_<split>" otherwise (metrics_test_ood.json)."""
  return "" if split == "test" else f"_{split}"


def run_test_and_ood(*, tokenizer_dir, diffusion_dir, data_dir, workdir, ddpm_scenarios: int,
                     ood_ddpm_scenarios: int, seed: int = 0, max_scenarios: int = 0,
                     baseline_dir=None, ddpm_diffusion_dir=None) -> dict:
  """Reports on test (metrics.json, results.md, ...) and, where the dataset has the split,
  on test_ood (metrics_test_ood.json, results_test_ood.md, ...) into one `workdir`, in
  the same schema; without test_ood a note is printed. Arguments as in `run`, with
  `ood_ddpm_scenarios` the DDPM baseline's subset on test_ood. Returns {split: metrics}."""
  splits = {"test": ddpm_scenarios}
  if "test_ood" in dataset_lib.split_names(data_dir):
    splits["test_ood"] = ood_ddpm_scenarios
  else:
    print(f"note: {data_dir} has no test_ood split (the highD and cvmd_mat sources have "
          "none); only the test split is evaluated", flush=True)
  return {split: run(tokenizer_dir=tokenizer_dir, diffusion_dir=diffusion_dir,
                     data_dir=data_dir, workdir=workdir, split=split, seed=seed,
                     max_scenarios=max_scenarios, ddpm_scenarios=ddpm,
                     suffix=split_suffix(split), baseline_dir=baseline_dir,
                     ddpm_diffusion_dir=ddpm_diffusion_dir)
          for split, ddpm in splits.items()}
