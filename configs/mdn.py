"""Mixture density baseline config (`cvmdx_jax.models.mdn`, beyond the paper).

Run (after make_dataset and train_tokenizer):
  .venv/bin/python experiments/train_mdn.py \\
      --config=configs/mdn.py:demo --workdir=runs/demo/mdn \\
      --config.data_dir=runs/demo/data --config.tokenizer_dir=runs/demo/tokenizer
Presets after the path: `:tiny` (seconds, tests), `:demo` (the `make demo` stage: within
90 s on 2 cores on the `:small` SUMO dataset, compile included). No preset: the demo model
with more epochs. The epoch with the lowest val mixture NLL is kept
(`cvmdx_jax.train.mdn`). Any field can be overridden: `--config.loss.warmup_epochs=3`;
the entry point checks every field once (`cvmdx_jax.config.mdn.MDNRunConfig`).
"""

import ml_collections

from configs import baseline, common


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  """Returns the mixture density baseline config for `arg` (see the module docstring)."""
  arg = common.parse_arg(arg, tiny=False, demo=False)
  # data, tokens, seed, the MLP trunk and mean heads and the optimiser: the multiple-choice
  # baseline's (configs/baseline.py), preset for preset
  config = baseline.get_config("tiny" if arg.tiny else None)
  # m, the smallest std of a position coordinate (0.02 m: better joint and 1 s NLL, worse
  # 3-5 s NLL and mean ADE on val; docs/log/2026-12-06-mdn-baseline.md)
  config.model.std_floor_m = 0.05
  config.loss = ml_collections.ConfigDict()
  # epochs of winner-takes-all warm-up (the MLP's loss) before the mixture NLL
  config.loss.warmup_epochs = 0
  config.loss.cls_weight = 1.0  # weight of the mode cross-entropy in the warm-up
  config.train.select_metric = "loss"  # the epoch with the lowest val mixture NLL is kept

  if arg.demo:
    # chosen on val by the lowest mixture NLL over two seeds: lr 2e-3 (-58.6 nats against
    # -50.0 for 1e-3), no warm-up (3 epochs: -35.9), 15 epochs (25: 3.5 nats lower at seed
    # 0, within the seeds' spread); ~40 s of CPU time on 2 cores, compile included
    config.train.num_epochs = 15
  return config
