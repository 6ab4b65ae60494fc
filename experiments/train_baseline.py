"""Trains the multiple-choice MLP baseline on (ego features, token q, delta) -> K trajectories.

  .venv/bin/python experiments/train_baseline.py --config=configs/baseline.py:demo \\
      --workdir=runs/demo/baseline --config.data_dir=... --config.tokenizer_dir=...
Rerunning the same command resumes from the last complete checkpoint. Evaluate it beside
cVMDx with `experiments/evaluate.py --baseline_dir=...`.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import jax
from absl import app, flags, logging
from ml_collections import config_flags

from cvmdx_jax import sharding
from cvmdx_jax.config.runs import BaselineRunConfig
from cvmdx_jax.train import baseline

_CONFIG = config_flags.DEFINE_config_file("config", None, "Baseline config file.", lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run directory (checkpoints, metrics).")
flags.mark_flags_as_required(["config", "workdir"])
cli.output_dirs("workdir")
_RUN = cli.typed_config("config", BaselineRunConfig.from_config)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  sharding.initialize_distributed()
  logging.info("JAX devices: %s", jax.devices())
  baseline.train(_RUN.value, _WORKDIR.value)


if __name__ == "__main__":
  cli.run(main, allocator=True)
