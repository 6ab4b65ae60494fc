"""Scenario tokeniser (CVQ-VAE + maneuver head) config.

Run:
  .venv/bin/python experiments/train_tokenizer.py \
      --config=configs/tokenizer.py --workdir=runs/tokenizer
Presets after the path: `:tiny` (seconds, for tests), `:demo` (CPU-sized, a few minutes on
2 cores on the ~7k-train-scenario small SUMO dataset), `:paper` (the paper's batch 64, lr 4.5e-6,
1200 epochs); no preset is the default. Shorthands: `:q=60,quantizer=vq`. Any field can
be overridden with `--config.<section>.<field>=<value>`, e.g.
`--config.quantizer.codebook_size=90 --config.train.num_epochs=50`. Sections: `model`
(`TokenizerConfig`), `quantizer` (`QuantizerConfig`; its latent_dim is
`model.encoder.latent_dim`), `uncertainty` (the Gaussians of delta), `train`.

The default departs from the paper in the learning rate: at the paper's 4.5e-6 the
tokeniser needs its 1200 epochs; the default uses Adam at 5e-4 (and gradient clipping) for
100 epochs (on the default SUMO set, Q = 60: 98 % train maneuver accuracy, 48 of 60
entries in use, 5 min on 2 cores; revive_strength 0.01 keeps 57 in use but reaches only
85 % accuracy). CVQ's revive_strength defaults to 0.1 instead of
Zheng & Vedaldi's 10: with 10, an entry must go unused for a few hundred steps before the
anchor pull acts, and in ~1,000-step runs on the small SUMO set 14 of 60 entries ended
dead (46/60 in use); with 0.1, 57/60 (measured with the :demo preset on the :small
SUMO dataset; revive_strength=1.0 gave 54/60).

`ego_weight` (30) weighs the ego's features in the reconstruction error against each
neighbour's (1): the diffusion model sees only the token, so the token must tell how
this vehicle is moving, not only where its neighbours are. With weight 1 the ego is 1/9
of the loss and the tokens told its acceleration and lateral drift poorly (token-mean
rollout ADE 1.51 m vs constant velocity 1.56 m on the :small test split; 1.33-1.41 m
with weight 30 and the velocity scales of `cvmdx_jax.models.scenario_norm`; BUILD_NOTES.md).
"""

import ml_collections

from configs import common


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  """Returns the tokeniser config for `arg` (see the module docstring)."""
  arg = common.parse_arg(arg, tiny=False, demo=False, paper=False, q=0, quantizer="")
  config = ml_collections.ConfigDict()
  config.data_dir = "data/sumo"  # dataset folder read by cvmdx_jax.data.dataset.load_split
  config.splits = ()  # splits tokenised after training (train is fitted on); () = every split
  config.seed = 0  # one seed for init, per-epoch shuffles and per-step keys
  config.encode_batch = 512  # scenarios per chunk when encoding whole splits

  config.model = ml_collections.ConfigDict()
  config.model.encoder = ml_collections.ConfigDict()
  config.model.encoder.latent_dim = 16  # D, size of z_hat and of each codebook entry
  config.model.encoder.channels = (64, 128, 128)  # conv widths of E and D, one stride-2 level each
  config.model.encoder.kernel_size = 5  # temporal kernel of every conv
  config.model.cls_weight = 1.0  # lambda, weight of the maneuver cross-entropy
  config.model.ego_weight = 30.0  # weight of the ego's features in the reconstruction error

  config.quantizer = ml_collections.ConfigDict()
  config.quantizer.kind = "cvq"  # "cvq" (online clustered codebook) or "vq" (plain VQ-VAE)
  config.quantizer.codebook_size = 60  # Q, number of scenario tokens; paper ablates 30..256
  config.quantizer.beta = 0.25  # commitment weight
  config.quantizer.usage_decay = 0.99  # CVQ: gamma of the running usage average
  config.quantizer.revive_strength = 0.1  # CVQ: how fast the anchor pull fades (Zheng: 10)

  config.uncertainty = ml_collections.ConfigDict()
  config.uncertainty.shrinkage = 16.0  # pseudo-members of the pooled covariance per entry
  config.uncertainty.ridge = 1e-3  # relative diagonal loading of the pooled covariance

  config.train = ml_collections.ConfigDict()
  config.train.batch_size = 64  # global batch (paper: 64)
  config.train.num_epochs = 100  # passes over the training split
  config.train.learning_rate = 5e-4  # Adam lr (paper: 4.5e-6 with 1200 epochs)
  config.train.grad_clip = 1.0  # global-norm gradient clipping
  config.train.checkpoint_every = 5  # epochs between checkpoints (and after the last)
  config.train.keep = 2  # checkpoints kept

  if arg.tiny:
    config.model.encoder.latent_dim = 4
    config.model.encoder.channels = (8, 8)
    config.model.encoder.kernel_size = 3
    config.quantizer.codebook_size = 8
    config.train.batch_size = 8
    config.train.num_epochs = 1
    config.train.learning_rate = 1e-3
    config.encode_batch = 16
    config.train.checkpoint_every = 1
  if arg.demo:
    config.model.encoder.channels = (32, 64, 64)
    config.train.batch_size = 64
    config.train.num_epochs = 15
    config.train.learning_rate = 1e-3
  if arg.paper:
    config.train.num_epochs = 1200
    config.train.learning_rate = 4.5e-6
    config.train.checkpoint_every = 50
  if arg.q:
    config.quantizer.codebook_size = arg.q
  if arg.quantizer:
    config.quantizer.kind = arg.quantizer
  return config
