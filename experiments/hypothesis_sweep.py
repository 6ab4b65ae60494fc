"""Hypothesis methods x sample counts on one trained run's validation split; picks the
default hypothesis method and N.

  .venv/bin/python experiments/hypothesis_sweep.py \\
      --tokenizer_dir=runs/demo/tokenizer --diffusion_dir=runs/demo/diffusion \\
      --data_dir=runs/demo/data --out_dir=runs/demo/hypothesis_sweep

The run's sampler draws max(--num_samples) samples per scenario once (seed --seed); the
setting with N samples uses the first N of them (the samples are independent, so these
are N samples of the model's distribution, as a run with num_samples = N draws). Each
--methods entry ("bic", or "kmeans:<endpoint_weight>") then forms hypotheses from them.
Cost: the prediction time per scenario of the full pipeline with N samples (the run's
sampler, BIC hypotheses) on --timing_scenarios scenarios after a warm-up call, and the
hypothesis step alone per method (jitted, after a warm-up), on this machine.

Choice rule: among the settings with N <= --max_num_samples (the cost bound) whose mean-of-N
ADE is within --tolerance of the reference's (the run's own N with "bic", today's default),
the lowest Brier-minFDE.
Writes <out_dir>/sweep.md and sweep.json.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags

from cvmdx_jax.config.sampling import MAX_SAMPLES, HypothesisConfig
from cvmdx_jax.data import dataset
from cvmdx_jax.errors import UserError
from cvmdx_jax.evaluation import scoring, sweeps
from cvmdx_jax.inference.predictor import Predictor, PredictorOutput
from cvmdx_jax.inference.sampling import Prediction
from cvmdx_jax.multimodal import fit_hypotheses
from cvmdx_jax.storage import atomic

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion run directory.")
_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory.")
_OUT = flags.DEFINE_string("out_dir", None, "Where sweep.md and sweep.json go.")
_SPLIT = flags.DEFINE_string("split", "val", "Split to evaluate (choose on val).")
_NUM = flags.DEFINE_integer(
    "num_scenarios", 0, "Class-balanced subset size (0 = all).", lower_bound=0
)
_SEED = flags.DEFINE_integer("seed", 0, "Sampling and subset seed.")
_SAMPLES = flags.DEFINE_list("num_samples", ["9", "18", "36", "64"], "Sample counts N.")
cli.int_list("num_samples", 1, MAX_SAMPLES)  # a count beyond would not fit in memory
_METHODS = flags.DEFINE_list(
    "methods", ["bic", "kmeans:0", "kmeans:0.5", "kmeans:1"], "'bic' or 'kmeans:<endpoint_weight>'."
)
_TIMING = flags.DEFINE_integer(
    "timing_scenarios", 64, "Scenarios of the timing calls.", lower_bound=1
)
_SAMPLES_FILE = flags.DEFINE_string(
    "samples_file",
    None,
    "An .npz of the samples: read if it exists (the sampling is "
    "skipped), else written after sampling, so that more methods can be scored later.",
)
_MAX_N = flags.DEFINE_integer(
    "max_num_samples",
    0,
    "Largest N the choice may take (the cost " "bound; 0 = any).",
    lower_bound=0,
)
_TOL = flags.DEFINE_float(
    "tolerance", 0.02, "Allowed relative mean-ADE loss vs the " "reference.", lower_bound=0.0
)


def _method(spec: str, base: HypothesisConfig) -> HypothesisConfig:
  try:
    return sweeps.hypothesis_config(spec, base)
  except ValueError as e:
    raise UserError(f"--methods: {e}") from None


def score(trajectories, config: HypothesisConfig, data) -> dict:
  """The sweep's columns (means over `data`) for samples (M, N, T, 2) and `config`."""
  hyp = fit_hypotheses(trajectories, config=config)
  pred = Prediction(
      controls=jnp.zeros_like(trajectories),
      trajectories=trajectories,
      mean=jnp.mean(trajectories, axis=1),
      hypotheses=hyp,
  )
  out = PredictorOutput(
      prediction=pred,
      q=np.zeros(len(data), int),
      delta=np.zeros(len(data)),
      out_of_distribution=np.zeros(len(data), bool),
  )
  gt = jnp.asarray(data.future)
  errors = scoring.cvmdx_errors(out, gt, data.label)
  ece, _ = scoring.calibration(hyp.means, hyp.probs, gt, data.label)
  mean, best = errors["cvmdx_mean"], errors["cvmdx_best_of_k"]
  row = {
      "mean_ade": mean["ade"],
      "mean_fde": mean["fde"],
      "min_ade_k": best["ade"],
      "min_fde_k": best["fde"],
      "brier_min_fde": best["brier_min_fde"],
      "energy_score": mean["energy_score"],
      "nll_final": best["nll_final"],
  }
  return {
      **{k: float(np.mean(v)) for k, v in row.items()},
      "ece": ece["all"]["ece"],
      "single_mode_share": float(np.mean(np.asarray(hyp.num_modes) == 1)),
  }


def seconds_per_scenario(fn, count: int) -> float:
  """Wall time of `fn()` (after one warm-up call) divided by `count`."""
  jax.block_until_ready(fn())
  start = time.perf_counter()
  jax.block_until_ready(fn())
  return (time.perf_counter() - start) / count


def sweep() -> tuple[list[dict], str, int]:
  """Every (N, method) row, a note on the data and the run's own N."""
  data = dataset.load_balanced(_DATA.value, _SPLIT.value, _SEED.value, _NUM.value)
  predictor = Predictor.load(_TOKENIZER.value, _DIFFUSION.value)
  counts = sorted(int(n) for n in _SAMPLES.value)
  configs = {spec: _method(spec, predictor.sampling.hypotheses) for spec in _METHODS.value}
  saved = Path(_SAMPLES_FILE.value) if _SAMPLES_FILE.value else None
  if saved and saved.is_file():
    samples = jnp.asarray(np.load(saved)["trajectories"])
    if samples.shape[:2] != (len(data), counts[-1]):
      raise UserError(
          f"--samples_file {saved}: shape {samples.shape} does not match "
          f"{len(data)} scenarios x {counts[-1]} samples"
      )
  else:
    full = dataclasses.replace(
        predictor, sampling=dataclasses.replace(predictor.sampling, num_samples=counts[-1])
    )
    samples = jnp.asarray(full(data, seed=_SEED.value).prediction.trajectories)
    if saved:
      atomic.write_npz(saved, trajectories=np.asarray(samples))
  timing = data.take(np.arange(min(_TIMING.value, len(data))))
  fit = jax.jit(fit_hypotheses, static_argnames=("c_max", "config"))
  rows = []
  for n in counts:
    at_n = dataclasses.replace(
        predictor, sampling=dataclasses.replace(predictor.sampling, num_samples=n)
    )
    predict_s = seconds_per_scenario(lambda: at_n(timing, seed=_SEED.value).mean, len(timing))
    for spec, config in configs.items():
      fit_s = seconds_per_scenario(lambda: fit(samples[:, :n], config=config).probs, len(data))
      rows.append(
          {
              "method": spec,
              "num_samples": n,
              "predict_s": predict_s,
              "hypotheses_s": fit_s,
              **score(samples[:, :n], config, data),
          }
      )
      print(rows[-1], flush=True)
  note = (
      f"{_DIFFUSION.value}, split {_SPLIT.value}, {len(data)} scenarios, seed "
      f"{_SEED.value}, sampler {predictor.sampling.sampler} S = {predictor.sampling.steps}, "
      f"reference: bic with N = {predictor.sampling.num_samples}"
  )
  return rows, note, predictor.sampling.num_samples


def main(argv):
  if len(argv) > 1:
    raise UserError(f"hypothesis_sweep: unexpected arguments {argv[1:]}")
  missing = [f.name for f in (_TOKENIZER, _DIFFUSION, _DATA, _OUT) if not f.value]
  if missing:
    raise UserError(f"hypothesis_sweep: flags {missing} are required")
  rows, note, predictor_n = sweep()
  ref = [r for r in rows if r["method"] == "bic" and r["num_samples"] == predictor_n]
  if not ref:
    raise UserError(
        f"hypothesis_sweep: the reference (bic, N = {predictor_n}) was not "
        "evaluated; include it in --methods and --num_samples"
    )
  choice = sweeps.choose_hypotheses(rows, ref[0], _TOL.value, _MAX_N.value)
  out = Path(_OUT.value)
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_json(
      out / "sweep.json",
      {
          "note": note,
          "tolerance": _TOL.value,
          "max_num_samples": _MAX_N.value,
          "rows": rows,
          "choice": choice,
      },
  )
  table = sweeps.hypotheses_table(rows, choice, note, _TOL.value, _MAX_N.value)
  atomic.write_text(out / "sweep.md", table)
  print(table)


if __name__ == "__main__":
  cli.run(main)
