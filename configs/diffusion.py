"""Motion diffusion model (U-Net denoiser + sampling) config.

Run (after make_dataset and train_tokenizer):
  .venv/bin/python experiments/train_diffusion.py \\
      --config=configs/diffusion.py:demo --workdir=runs/demo/diffusion \\
      --config.data_dir=runs/demo/data --config.tokenizer_dir=runs/demo/tokenizer
Presets after the path: `:tiny` (seconds, tests), `:demo` (the CPU default of the
`make demo` pipeline: a small U-Net trained for a few minutes on 2 cores), `:paper`
(the reference U-Net: 128 channels, (1, 2, 3, 4), attention at the two coarsest
levels; batch 256, lr 2e-4, 2000 epochs: a GPU job), `:reference` (as paper, but with
attention only in the middle block, which is what the official code's
attention_resolutions="16,8" yields for length 125: its 22.5 M parameters).
No preset: the paper model with a CPU-feasible epoch count, sampled with DPM-Solver++(2M)
in 3 steps (:paper and :reference: the paper's DDIM-10). Any field can be
overridden: `--config.sampling.steps=20`, `--config.train.num_epochs=50`.
"""

import ml_collections

from configs import common


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  """Returns the diffusion config for `arg` (see the module docstring)."""
  arg = common.parse_arg(arg, tiny=False, demo=False, paper=False, reference=False)
  config = ml_collections.ConfigDict()
  config.data_dir = "data/sumo"  # dataset folder (cvmdx_jax.data.dataset)
  config.tokenizer_dir = "runs/tokenizer"  # tokeniser run whose tokens condition the model
  config.seed = 0  # init, example order, step keys

  config.model = _model()
  config.diffusion = _diffusion()
  config.train = _train()
  config.sampling = _sampling()
  if arg.tiny:
    _tiny(config)
  if arg.demo:
    _demo(config)
  if arg.paper or arg.reference:
    config.train.num_epochs = 2000
    config.train.checkpoint_every = 50
  else:  # the fewest U-Net evaluations within 2 % of DDIM-10 on val:
    # docs/results.md#samplers-u-net-evaluations-against-accuracy
    config.sampling.sampler = "dpmpp2m"
    config.sampling.steps = 3
  if arg.reference:
    config.model.attention_levels = ()
  return config


def _model() -> ml_collections.ConfigDict:
  """The U-Net: the paper's reference size."""
  model = ml_collections.ConfigDict()
  model.base_channels = 128  # channels at the finest level
  model.channel_mult = (1, 2, 3, 4)  # per-level multipliers
  model.num_res_blocks = 1  # residual blocks per level
  model.emb_mult = 2  # embedding width / base_channels (reference: 2)
  model.attention_levels = (2, 3)  # levels with self-attention
  model.num_heads = 4  # attention heads
  model.groups = 32  # GroupNorm groups
  model.dropout = 0.0  # residual-block dropout (reference: 0)
  # hidden layer widths of the MLP of the ego-motion features (conditionings "ego_film*";
  # beyond the paper); () = one layer of the embedding width
  model.cond_hidden = ()
  return model


def _diffusion() -> ml_collections.ConfigDict:
  """What the denoiser is: schedule, targets, conditioning (the paper's)."""
  diffusion = ml_collections.ConfigDict()
  diffusion.num_steps = 1000  # T of the cosine schedule
  diffusion.cond_drop_prob = 0.1  # CFG conditioning dropout (paper 10 %, ref 20 %)
  # [a_x m/s^2, yaw rate rad/s] per normalised unit (targets clipped to [-1, 1]); paper
  # (4, 0.7). Highway yaw rates stay below 0.075 rad/s in 99.9 % of steps, so 0.7 leaves
  # 90 % of the range unused: a small model's error then costs metres laterally.
  diffusion.control_scale = (4.0, 0.7)
  # what the denoiser sees besides x_t and t (cvmdx_jax/ego_motion.py): "token" (the paper),
  # "ego_film" (+ ego-motion features as a FiLM embedding), "ego_residual" (target =
  # controls minus the ego's current [a_x, yaw rate] extrapolated), "ego_film_residual".
  # Guidance drops only the token: both CFG branches see the ego features.
  diffusion.conditioning = "token"
  # (a_x, yaw rate) decay time constants [s] of the extrapolated current controls of the
  # residual target: the current acceleration persists for seconds, the yaw rate (from
  # 0.01 m/s velocity steps) for a few steps; tau_a chosen on val from 2 / 3 / 5 s with the
  # demo model, tau_r on train (docs/log, "Residual base")
  diffusion.residual_decay_s = (3.0, 0.1)
  # loss weight per maneuver class (keep lane, lane change right, lane change left) of the
  # training scenarios; the weighted loss fits the denoiser to the class mixture
  # reweighted by them (beyond the paper, which trains on the balanced classes: (1, 1, 1))
  diffusion.class_weights = (1.0, 1.0, 1.0)
  # the U-Net also sees the maneuver class (keep lane, lcr, lcl; one-hot after the ego
  # features): the true one in training, one a sample drawn from an intent classifier on
  # the ego features (trained beside it) in sampling; needs ego_film*; beyond the paper
  diffusion.intent_conditioning = False
  return diffusion


def _train() -> ml_collections.ConfigDict:
  """The training loop: the paper's batch and learning rate, a CPU-feasible epoch count."""
  train = ml_collections.ConfigDict()
  train.batch_size = 256  # global batch (paper)
  train.num_epochs = 100  # paper: 2000
  train.learning_rate = 2e-4  # peak AdamW lr (paper)
  train.warmup_steps = 3000  # linear warm-up (reference); capped at 10 % of the run
  train.min_lr = 1e-6  # end of the cosine decay (reference)
  train.weight_decay = 0.0  # AdamW decoupled weight decay (reference: 0)
  train.grad_clip = 1.0  # global-norm clipping
  train.ema_decay = 0.9999  # EMA of the weights used for inference (reference)
  train.checkpoint_every = 5  # epochs between checkpoints
  train.keep = 2  # checkpoints kept
  return train


def _sampling() -> ml_collections.ConfigDict:
  """The paper's sampling: N = 9, DDIM-10, its guidance and hypotheses."""
  sampling = ml_collections.ConfigDict()
  sampling.num_samples = 9  # N samples per scenario (paper)
  # "ddim" (S steps), "ddpm" (all T), "dpmpp2m" (DPM-Solver++(2M) over the same guided
  # ODE, S guided evaluations; beyond the paper) or "distilled" (a distilled student's)
  sampling.sampler = "ddim"  # paper
  # "paper" (the paper's equations) or "official" (the official code's guided DDIM loop:
  # steps - 1 updates, w from w_min to w_max_base by step index, no delta; README)
  sampling.mode = "paper"
  sampling.steps = 10  # S DDIM / DPM-Solver++ steps (paper: DDIM 10)
  sampling.eta = 0.0  # DDIM noise
  sampling.clip_x0 = 1.0  # clip predicted x0 to [-1, 1] (official sampler); 0 = off
  # weights (keep lane, lcr, lcl) on an intent conditioning's class probabilities before
  # its draws: the ratio of the class shares where the model is used to its train split's
  sampling.intent_prior = (1.0, 1.0, 1.0)
  sampling.guidance = ml_collections.ConfigDict()
  sampling.guidance.w_min = 0.1  # paper
  sampling.guidance.w_max_base = 1.0  # paper
  sampling.guidance.t_c = 50.0  # paper
  sampling.guidance.form = "paper"  # "paper" (1+w)c - w u, or "official" u + w (c - u)
  sampling.guidance.direction = "paper"  # "paper" or "official" (reversed cosine)
  sampling.hypotheses = ml_collections.ConfigDict()
  # "bic" (the paper's PCA + GMM + BIC over C = 1..C_max) or "kmeans" (k-means with
  # K = C_max over the trajectories, built to cover the true future; beyond the paper)
  sampling.hypotheses.method = "bic"
  sampling.hypotheses.c_max = 3  # C_max (paper)
  sampling.hypotheses.scaling = "physical"  # "physical" (x/180, y/7) or "minmax"
  sampling.hypotheses.x_scale = 180.0  # m, physical scaling
  sampling.hypotheses.y_scale = 7.0  # m, physical scaling
  sampling.hypotheses.pca_dim = 2  # r (paper)
  sampling.hypotheses.reg_covar = 1e-2  # covariance floor in scaled PCA units
  sampling.hypotheses.em_iters = 30  # EM iterations per C
  sampling.hypotheses.kmeans_iters = 10  # Lloyd steps of "kmeans"
  # weight of the 5 s position in the k-means distance (0 = mean over the 125 steps)
  sampling.hypotheses.endpoint_weight = 0.0
  # p(c) = share^t / sum over the hypotheses (1: the paper's share of samples)
  sampling.hypotheses.prob_temperature = 1.0
  return sampling


def _tiny(config: ml_collections.ConfigDict) -> None:
  """`:tiny`: a U-Net that trains in seconds (tests)."""
  config.model.base_channels = 16
  config.model.channel_mult = (1, 2)
  config.model.attention_levels = (1,)
  config.model.num_heads = 2
  config.model.groups = 8
  config.train.batch_size = 16
  config.train.num_epochs = 1
  config.train.learning_rate = 1e-3
  config.train.checkpoint_every = 1


def _demo(config: ml_collections.ConfigDict) -> None:
  """`:demo`: every choice made on val (docs/results.md#demo-choices)."""
  config.model.base_channels = 32  # a U-Net that trains in minutes on 2 cores
  config.model.channel_mult = (1, 2, 2, 2)
  config.model.attention_levels = (3,)
  config.model.groups = 8
  config.model.cond_hidden = (256, 256)  # docs/results.md#demo-choices, conditioning MLP
  config.train.batch_size = 128  # docs/results.md#demo-choices, batch
  config.train.num_epochs = 30  # docs/results.md#demo-choices, epochs (15 min budget)
  config.train.learning_rate = 1e-3
  config.train.warmup_steps = 200
  config.train.ema_decay = 0.999
  # a save costs ~2 s on 2 cores (orbax writes the state's ~900 arrays one by one): 3 in the
  # demo, not 6; SIGTERM and Ctrl-C still save at the next step
  config.train.checkpoint_every = 10
  config.diffusion.control_scale = (4.0, 0.1)  # docs/results.md#demo-choices, yaw scale
  config.diffusion.conditioning = "ego_film_residual"  # docs/results.md#demo-choices
  config.diffusion.intent_conditioning = True  # docs/results.md#demo-choices, intent
  config.sampling.guidance.w_min = 0.0  # docs/results.md#demo-choices, guidance
  config.sampling.guidance.w_max_base = 0.0
  config.sampling.intent_prior = (2.0, 1.0, 1.0)  # docs/results.md#demo-choices, prior
  config.sampling.num_samples = 64  # docs/results.md#demo-choices, hypotheses
  config.sampling.hypotheses.method = "kmeans"
  config.sampling.hypotheses.endpoint_weight = 0.5
  config.sampling.hypotheses.prob_temperature = 0.6  # docs/results.md#demo-choices, p(c)
