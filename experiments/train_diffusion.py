"""Trains the motion diffusion model on (normalised controls, token q).

  .venv/bin/python experiments/train_diffusion.py --config=configs/diffusion.py:demo \\
      --workdir=runs/demo/diffusion --config.data_dir=... --config.tokenizer_dir=...
Rerunning the same command resumes from the last complete checkpoint.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import jax
from absl import app, flags, logging
from ml_collections import config_flags

from cvmdx_jax import sharding
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.train import diffusion

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Diffusion config file.", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run directory (checkpoints, metrics).")
flags.mark_flags_as_required(["config", "workdir"])
cli.output_dirs("workdir")
_RUN = cli.typed_config("config", DiffusionRunConfig.from_config)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  sharding.initialize_distributed()
  logging.info("JAX devices: %s", jax.devices())
  diffusion.train(_RUN.value, _WORKDIR.value)


if __name__ == "__main__":
  cli.run(main, allocator=True)
