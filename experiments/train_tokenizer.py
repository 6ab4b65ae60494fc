"""Trains the scenario tokeniser (CVQ-VAE / VQ-VAE + maneuver head) and writes its tokens.

  .venv/bin/python experiments/train_tokenizer.py \
      --config=configs/tokenizer.py:demo --workdir=runs/tokenizer
Rerunning the same command resumes from the latest checkpoint in --workdir. The library
does the work (cvmdx_jax.train.tokenizer); this file only parses flags.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import jax
from absl import app, flags, logging
from ml_collections import config_flags

from cvmdx_jax import sharding
from cvmdx_jax.config.runs import TokenizerRunConfig
from cvmdx_jax.train import tokenizer

_CONFIG = config_flags.DEFINE_config_file(
    "config", None, "Tokeniser config file, e.g. configs/tokenizer.py:tiny.", lock_config=True
)
_WORKDIR = flags.DEFINE_string("workdir", None, "Run directory (checkpoints, metrics, tokens).")
flags.mark_flags_as_required(["config", "workdir"])
cli.output_dirs("workdir")
_RUN = cli.typed_config("config", TokenizerRunConfig.from_config)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Too many command-line arguments: {argv[1:]}")
  sharding.initialize_distributed()
  logging.info("devices: %s", jax.devices())
  tokenizer.train(_RUN.value, _WORKDIR.value)
  logging.info("tokens written to %s/tokens", _WORKDIR.value)


if __name__ == "__main__":
  cli.run(main, allocator=True)
