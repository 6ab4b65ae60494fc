"""Multiple-choice MLP baseline config (`cvmdx_jax.models.multiple_choice`, beyond the paper).

Run (after make_dataset and train_tokenizer):
  .venv/bin/python experiments/train_baseline.py \\
      --config=configs/baseline.py:demo --workdir=runs/demo/baseline \\
      --config.data_dir=runs/demo/data --config.tokenizer_dir=runs/demo/tokenizer
Presets after the path: `:tiny` (seconds, tests), `:demo` (the `make demo` stage: within
90 s on 2 cores on the `:small` SUMO dataset, compile included). No preset: the demo model
with more epochs. The epoch is chosen on val (`train.select_metric`;
`cvmdx_jax.train.baseline`). Any field can be overridden: `--config.train.num_epochs=50`;
the entry point checks every field once (`cvmdx_jax.config.runs.BaselineRunConfig`).
"""

import ml_collections

from configs import common


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  """Returns the baseline config for `arg` (see the module docstring)."""
  arg = common.parse_arg(arg, tiny=False, demo=False)
  config = ml_collections.ConfigDict()
  config.data_dir = "data/sumo"  # dataset folder (cvmdx_jax.data.dataset)
  config.tokenizer_dir = "runs/tokenizer"  # tokeniser run whose tokens q and delta it reads
  config.seed = 0  # init, example order

  config.model = ml_collections.ConfigDict()
  config.model.num_hypotheses = 3  # K heads (= cVMDx's C_max)
  config.model.token_dim = 16  # width of the learned token embedding
  config.model.hidden = (256, 256)  # hidden layer widths (GELU)
  # [a_x m/s^2, yaw rate rad/s] per unit of a head's output: the demo denoiser's scale
  config.model.control_scale = (4.0, 0.1)
  # (tau_a, tau_r) s of the residual base the heads add to: the demo denoiser's
  config.model.residual_decay_s = (3.0, 0.1)

  config.loss = ml_collections.ConfigDict()
  config.loss.cls_weight = 1.0  # weight of the mode cross-entropy beside the winner's ADE (m)

  config.train = ml_collections.ConfigDict()
  config.train.batch_size = 256  # global batch
  config.train.num_epochs = 30  # epochs; the best on val is kept
  config.train.learning_rate = 2e-3  # peak AdamW lr
  config.train.warmup_steps = 100  # linear warm-up; capped at 10 % of the run
  config.train.end_lr_fraction = 0.01  # end of the cosine decay, as a fraction of the peak
  config.train.weight_decay = 1e-4  # AdamW decoupled weight decay
  config.train.grad_clip = 1.0  # global-norm clipping
  # val read-out whose lowest value picks the epoch (cvmdx_jax.config.runs.SELECT_METRICS)
  config.train.select_metric = "min_ade"
  config.train.checkpoint_every = 10  # epochs between checkpoints (and after the last)
  config.train.keep = 1  # checkpoints kept (the state holds the val-chosen parameters)

  if arg.tiny:
    config.model.token_dim = 4
    config.model.hidden = (16,)
    config.train.batch_size = 8
    config.train.num_epochs = 2
    config.train.warmup_steps = 1
    config.train.checkpoint_every = 1
  if arg.demo:
    # 15 epochs (~430 steps on the :small train split): val minADE_K 0.468 m, as with 40
    # epochs at batch 128 (0.469) and better than 20 epochs (0.486) (BUILD_NOTES.md,
    # "Learned baseline"); ~41 s of CPU time on 2 cores, compile included
    config.train.num_epochs = 15
  return config
