"""Trains the mixture density baseline on (ego features, token q, delta) -> a mixture of K
Gaussian trajectories.

  .venv/bin/python experiments/train_mdn.py --config=configs/mdn.py:demo \\
      --workdir=runs/demo/mdn --config.data_dir=... --config.tokenizer_dir=...
Rerunning the same command resumes from the last complete checkpoint. Load the trained
model with `cvmdx_jax.inference.mdn_baseline.load_mdn`.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import jax
from absl import app, flags, logging
from ml_collections import config_flags

from cvmdx_jax import sharding
from cvmdx_jax.config.mdn import MDNRunConfig
from cvmdx_jax.train import mdn

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Mixture density baseline config " "file.", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run directory (checkpoints, metrics).")
flags.mark_flags_as_required(["config", "workdir"])
cli.output_dirs("workdir")
_RUN = cli.typed_config("config", MDNRunConfig.from_config)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  sharding.initialize_distributed()
  logging.info("JAX devices: %s", jax.devices())
  mdn.train(_RUN.value, _WORKDIR.value)


if __name__ == "__main__":
  cli.run(main, allocator=True)
