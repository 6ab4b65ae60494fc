"""Distils a trained denoiser run into a few-step student (one stage per run).

  .venv/bin/python experiments/distill.py --config=configs/distill.py:demo \\
      --config.teacher_dir=runs/demo/diffusion --workdir=runs/demo/distill
The workdir is a diffusion run directory of the student (sampler "distilled"):
`experiments/evaluate.py --diffusion_dir=<workdir>` and `Predictor.load` take it. Rerunning
the same command resumes from the last complete checkpoint; a workdir distilled from
another teacher is refused.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import jax
from absl import app, flags, logging
from ml_collections import config_flags

from cvmdx_jax import sharding
from cvmdx_jax.config.runs import DistillRunConfig
from cvmdx_jax.train import distill

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Distillation config file.", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run directory of the student.")
flags.mark_flags_as_required(["config", "workdir"])
cli.output_dirs("workdir")
_RUN = cli.typed_config("config", DistillRunConfig.from_config)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  sharding.initialize_distributed()
  logging.info("JAX devices: %s", jax.devices())
  distill.train(_RUN.value, _WORKDIR.value)


if __name__ == "__main__":
  cli.run(main, allocator=True)
