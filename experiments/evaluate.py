"""Evaluates trained cVMDx runs like the paper and writes metrics.json, tables, figures.

  .venv/bin/python experiments/evaluate.py --tokenizer_dir=runs/demo/tokenizer \\
      --diffusion_dir=runs/demo/diffusion --data_dir=runs/demo/data --split=test \\
      --workdir=runs/demo/eval
`--sampler=ddim --steps=10` samples with the paper's DDIM-10 instead of the run's sampler.
`--intent_prior=4,1,1` reweights an intent-conditioned denoiser's maneuver draws (keep lane,
lcr, lcl) for data whose class shares differ from its train split's. `--prob_temperature=0.6`
predicts p(c) with that temperature (experiments/calibrate_probs.py chooses it on val).
`--baseline_dir=runs/demo/baseline` adds the rows of a trained multiple-choice baseline
(experiments/train_baseline.py, on the same tokeniser); `--mdn_dir=runs/demo/mdn` those of
the mixture density network (experiments/train_mdn.py). results.md ends with the paired
differences of cVMDx against every baseline, with 95 % vehicle-bootstrap intervals.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

from absl import app, flags

from cvmdx_jax.config.sampling import SAMPLERS, SamplingConfig
from cvmdx_jax.evaluation import report

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion run directory.")
_DDPM_DIR = flags.DEFINE_string(
    "ddpm_diffusion_dir",
    None,
    "The run that draws the single-DDPM "
    "baseline (default: --diffusion_dir; for a distilled student, "
    "the guided denoiser it was distilled from).",
)
_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory.")
_WORKDIR = flags.DEFINE_string("workdir", None, "Output directory of the report.")
_BASELINE = flags.DEFINE_string(
    "baseline_dir",
    None,
    "Trained multiple-choice baseline run " "whose rows join the report (none: no rows).",
)
_MDN = flags.DEFINE_string(
    "mdn_dir",
    None,
    "Trained mixture density network run whose rows " "join the report (none: no rows).",
)
_SPLIT = flags.DEFINE_string("split", "test", "Split to evaluate.")
_SEED = flags.DEFINE_integer("seed", 0, "Sampling seed.", lower_bound=0, upper_bound=2**32 - 1)
_MAX = flags.DEFINE_integer(
    "max_scenarios", 0, "Class-balanced subset size (0 = all).", lower_bound=0
)
_DDPM = flags.DEFINE_integer(
    "ddpm_scenarios",
    300,
    "Scenarios for the single-DDPM-sample baseline (0 = skip).",
    lower_bound=0,
)
_SAMPLER = flags.DEFINE_enum(
    "sampler",
    None,
    list(SAMPLERS),
    "Sampler instead of the diffusion run's (e.g. ddim with "
    "--steps=10: the paper's DDIM-10 on a model whose default is "
    "dpmpp2m).",
)
_STEPS = flags.DEFINE_integer("steps", None, "Sampling steps instead of the run's.", lower_bound=1)
_TEMPERATURE = flags.DEFINE_float(
    "prob_temperature",
    None,
    "p(c) temperature of the hypotheses instead of the run's "
    "(experiments/calibrate_probs.py chooses one on val).",
    lower_bound=1e-3,
)
_PRIOR = flags.DEFINE_list(
    "intent_prior",
    None,
    "Weights (keep lane, lcr, lcl) on an intent "
    "conditioning's class probabilities instead of the run's: the "
    "ratio of the evaluated data's class shares to the train split's.",
)
flags.mark_flags_as_required(["tokenizer_dir", "diffusion_dir", "data_dir", "workdir"])
cli.input_dirs(
    "tokenizer_dir", "diffusion_dir", "data_dir", "baseline_dir", "mdn_dir", "ddpm_diffusion_dir"
)
cli.output_dirs("workdir")


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  overrides = {
      k: v
      for k, v in (
          ("sampler", _SAMPLER.value),
          ("steps", _STEPS.value),
          ("prob_temperature", _TEMPERATURE.value),
      )
      if v is not None
  }
  if _PRIOR.value is not None:
    try:
      overrides["intent_prior"] = SamplingConfig(
          intent_prior=tuple(float(w) for w in _PRIOR.value)
      ).intent_prior
    except ValueError as error:
      raise app.UsageError(f"--intent_prior={','.join(_PRIOR.value)}: {error}") from error
  report.run(
      tokenizer_dir=_TOKENIZER.value,
      diffusion_dir=_DIFFUSION.value,
      data_dir=_DATA.value,
      workdir=_WORKDIR.value,
      split=_SPLIT.value,
      seed=_SEED.value,
      max_scenarios=_MAX.value,
      ddpm_scenarios=_DDPM.value,
      sampling_overrides=overrides,
      baseline_dir=_BASELINE.value,
      mdn_dir=_MDN.value,
      ddpm_diffusion_dir=_DDPM_DIR.value,
  )
  print(open(f"{_WORKDIR.value}/results.md").read())


if __name__ == "__main__":
  cli.run(main)
