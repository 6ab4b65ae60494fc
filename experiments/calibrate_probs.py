"""Chooses the p(c) temperature of a trained run on val (temperature scaling).

  .venv/bin/python experiments/calibrate_probs.py --tokenizer_dir=runs/demo/tokenizer \\
      --diffusion_dir=runs/demo/student_progressive_1 --data_dir=runs/demo/data --split=val

Predicts the split once with the run's sampling at temperature 1 (p(c) = share of samples),
then prints, for each temperature of the grid, the mean log loss of the hypothesis closest
to the truth at 5 s (the criterion), the reliability's ECE, the hypotheses' energy score
and Brier-minFDE, and the chosen temperature: give it to a run's config
(`--config.sampling.hypotheses.prob_temperature`) or to evaluate.py / benchmark_quality.py
(`--prob_temperature`). `--out` also writes the table as JSON.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import jax.numpy as jnp
import numpy as np
from absl import app, flags

from cvmdx_jax.data import dataset
from cvmdx_jax.evaluation import prob_calibration, scoring
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.multimodal import hypotheses
from cvmdx_jax.storage import atomic

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion (or student) run directory.")
_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory.")
_SPLIT = flags.DEFINE_string("split", "val", "Split that chooses (a validation split).")
_MAX = flags.DEFINE_integer(
    "max_scenarios", 0, "Class-balanced subset size (0 = all).", lower_bound=0
)
_SEED = flags.DEFINE_integer("seed", 0, "Sampling seed.", lower_bound=0, upper_bound=2**32 - 1)
_OUT = flags.DEFINE_string("out", None, "JSON file for the table (optional).")
flags.mark_flags_as_required(["tokenizer_dir", "diffusion_dir", "data_dir"])
cli.input_dirs("tokenizer_dir", "diffusion_dir", "data_dir")


def table(out, future) -> list[dict]:
  """Per temperature of the grid: log loss, ECE, energy score, Brier-minFDE (means)."""
  hyp, gt = out.hypotheses, jnp.asarray(future)
  closest = prob_calibration.closest_hypothesis(hyp.means, hyp.probs, gt)
  losses = prob_calibration.log_losses(hyp.probs, closest)
  labels = np.zeros(len(gt), int)
  rows = []
  for t, loss in zip(prob_calibration.TEMPERATURES, losses):
    probs = hypotheses.temper(hyp.probs, t)
    best = scoring.best_of_k_errors(hyp.means, probs, gt, labels)
    ece, _ = scoring.calibration(hyp.means, probs, gt, labels)
    rows.append(
        {
            "temperature": t,
            "log_loss": float(loss),
            "ece": float(ece["all"]["ece"]),
            "energy_score": float(np.mean(best["energy_score"])),
            "brier_min_fde": float(np.mean(best["brier_min_fde"])),
        }
    )
  return rows


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  predictor = prob_calibration.with_temperature(
      Predictor.load(_TOKENIZER.value, _DIFFUSION.value), 1.0
  )
  scenarios = dataset.load_balanced(_DATA.value, _SPLIT.value, _SEED.value, _MAX.value)
  rows = table(predictor(scenarios, seed=_SEED.value), scenarios.future)
  chosen = prob_calibration.choose([r["log_loss"] for r in rows])
  print(f"{len(scenarios)} scenarios of {_SPLIT.value}")
  print("| temperature | log loss [nats] | ECE | energy score [m] | Brier-minFDE [m] |")
  print("|---|---|---|---|---|")
  for r in rows:
    print(
        f"| {r['temperature']:.1f} | {r['log_loss']:.4f} | {r['ece']:.4f} | "
        f"{r['energy_score']:.4f} | {r['brier_min_fde']:.4f} |"
    )
  print(f"chosen: prob_temperature={chosen:g} (the lowest log loss of the closest hypothesis)")
  if _OUT.value:
    atomic.write_json(_OUT.value, {"split": _SPLIT.value, "rows": rows, "chosen": chosen})


if __name__ == "__main__":
  cli.run(main)
