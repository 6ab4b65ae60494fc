"""Training of the motion diffusion model v_theta(x_t, t, q) on the shared loop.

Targets: normalised controls x0 = clip([a_x / 4, yaw_rate / 0.7], -1, 1), (M, 125, 2)
(with an `ego_*residual` conditioning: of controls minus the ego's extrapolated current
controls); condition: the tokeniser's token q of each training scenario (and, with an
`ego_film*` conditioning, its ego-motion features, `cvmdx_jax.ego_motion`). Loss: the
v-loss with conditioning dropout (of the token only) to the null token Q. Optimiser:
AdamW with linear warm-up and cosine decay to `min_lr`, global-norm clipping; an EMA of
the weights (with the usual warm-up of the decay, min(decay, (1 + step) / (10 + step))) is
what inference uses.
"""

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax

from cvmdx_jax import atomic, ego_motion, normalization, tokens as tokens_lib
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.diffusion import GuidanceConfig, cosine_schedule, v_loss
from cvmdx_jax.inference import SamplingConfig
from cvmdx_jax.models import unet1d
from cvmdx_jax.multimodal import HypothesisConfig
from cvmdx_jax.train import loop


def conditioning(config: ml_collections.ConfigDict) -> str:
  """The run's `diffusion.conditioning` ("token" for runs made before it existed)."""
  return ego_motion.check_conditioning(config.diffusion.get("conditioning", "token"))


def unet_config(config: ml_collections.ConfigDict, num_tokens: int) -> unet1d.UNetConfig:
  m = config.model
  cond_dim = ego_motion.NUM_FEATURES if ego_motion.uses_film(conditioning(config)) else 0
  return unet1d.UNetConfig(num_tokens=num_tokens, base_channels=m.base_channels,
                           channel_mult=tuple(m.channel_mult), num_res_blocks=m.num_res_blocks,
                           emb_mult=m.emb_mult, attention_levels=tuple(m.attention_levels),
                           num_heads=m.num_heads, groups=m.groups, dropout=m.dropout,
                           cond_dim=cond_dim)


def sampling_config(config: ml_collections.ConfigDict) -> SamplingConfig:
  s = config.sampling
  return SamplingConfig(
      num_samples=s.num_samples, sampler=s.sampler, steps=s.steps, eta=s.eta,
      clip_x0=s.clip_x0 if s.clip_x0 > 0 else None,
      control_scale=tuple(config.diffusion.control_scale),
      conditioning=conditioning(config),
      residual_decay_s=tuple(config.diffusion.get("residual_decay_s",
                                                 SamplingConfig.residual_decay_s)),
      guidance=GuidanceConfig(**s.guidance.to_dict()),
      hypotheses=HypothesisConfig(**s.hypotheses.to_dict()))


def optimizer(config: ml_collections.ConfigDict, total_steps: int):
  t = config.train
  warmup = min(t.warmup_steps, max(total_steps // 10, 1))
  lr = optax.warmup_cosine_decay_schedule(
      init_value=t.learning_rate * 0.01, peak_value=t.learning_rate, warmup_steps=warmup,
      decay_steps=max(total_steps, warmup + 1), end_value=t.min_lr)
  return optax.chain(optax.clip_by_global_norm(t.grad_clip),
                     optax.adamw(lr, weight_decay=t.weight_decay))


def make_init_fn(cfg: unet1d.UNetConfig, tx):
  """init_fn(key) -> {params, ema_params, opt_state, step}."""

  def init_fn(key):
    _, params = unet1d.init_unet(cfg, key)
    # a copy, so that donating the state never donates one buffer twice
    return {"params": params, "ema_params": jax.tree.map(jnp.copy, params),
            "opt_state": tx.init(params),
            "step": jnp.zeros((), jnp.int32)}
  return init_fn


def make_step_fn(graphdef, cfg: unet1d.UNetConfig, tx, *, cond_drop_prob: float,
                 ema_decay: float, num_steps: int):
  """The pure train step of the shared loop: v-loss, AdamW update, EMA."""
  schedule = cosine_schedule(num_steps)

  def step_fn(state, batch, key):
    k_loss, k_drop = jax.random.split(key)

    def loss_fn(params):
      ego = batch["ego"] if cfg.cond_dim else None
      model = lambda x_t, t, q: unet1d.apply_unet(graphdef, params, x_t, t, q, k_drop, ego)
      return v_loss(model, batch["x0"], batch["q"], k_loss, schedule, null_cond=cfg.null_token,
                    cond_drop_prob=cond_drop_prob, weight=batch["weight"])

    loss, grads = jax.value_and_grad(loss_fn)(state["params"])
    updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    step = state["step"] + 1
    decay = jnp.minimum(ema_decay, (1.0 + step) / (10.0 + step))
    ema = jax.tree.map(lambda e, p: decay * e + (1.0 - decay) * p, state["ema_params"], params)
    new = {"params": params, "ema_params": ema, "opt_state": opt_state, "step": step}
    return new, {"loss": loss, "grad_norm": optax.tree.norm(grads)}

  return step_fn


def fingerprint(config, cfg: unet1d.UNetConfig, dataset_id: str, tokens_meta: dict) -> dict:
  """What a checkpoint belongs to: model shape, dataset and tokeniser checkpoint."""
  checkpoint = tokens_meta.get("checkpoint", {})
  out = {"model": dataclasses.asdict(cfg), "num_diffusion_steps": config.diffusion.num_steps,
         "control_scale": list(config.diffusion.control_scale),
         "dataset_id": dataset_id,
         "tokenizer": {"fingerprint": checkpoint.get("fingerprint"),
                       "step": checkpoint.get("step")}}
  if conditioning(config) != "token":  # token-only fingerprints stay as they were
    out["conditioning"] = {"name": conditioning(config), "features": ego_motion.NUM_FEATURES,
                           "residual_decay_s": list(config.diffusion.residual_decay_s)}
  return out


def training_data(config) -> tuple[dict, int, str, dict]:
  """(arrays {x0, q[, ego]}, Q, dataset id, tokens metadata) of the training split."""
  scenarios = dataset_lib.load_split(config.data_dir, "train")
  dataset_id = dataset_lib.dataset_id(config.data_dir)
  toks, meta = tokens_lib.load_tokens(tokens_lib.tokens_path(config.tokenizer_dir, "train"),
                                      dataset_id=dataset_id, num_scenarios=len(scenarios))
  scale = tuple(config.diffusion.control_scale)
  data, controls = {"q": toks.q.astype(np.int32)}, scenarios.controls
  if conditioning(config) != "token":
    data["ego"] = np.asarray(ego_motion.ego_features(scenarios.xi, scenarios.mask))
    if ego_motion.uses_residual(conditioning(config)):
      controls = controls - ego_motion.residual_controls(
          data["ego"], tuple(config.diffusion.residual_decay_s))
  data["x0"] = np.asarray(normalization.normalize_controls(controls, scale), np.float32)
  return data, int(meta["codebook_size"]), dataset_id, meta


def init_and_step(config, cfg: unet1d.UNetConfig, total_steps: int):
  """(graphdef, init_fn, step_fn) of a run with `total_steps` optimiser steps."""
  graphdef = unet1d.make_graphdef(cfg)
  tx = optimizer(config, total_steps)
  step_fn = make_step_fn(graphdef, cfg, tx, cond_drop_prob=config.diffusion.cond_drop_prob,
                         ema_decay=config.train.ema_decay, num_steps=config.diffusion.num_steps)
  return graphdef, make_init_fn(cfg, tx), step_fn


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str | os.PathLike):
  """Trains the denoiser into `workdir` (resuming if possible); returns the final state.

  `workdir` gets `config.json` (the run's config), `model.json` (U-Net config and
  optimiser length, what `load_denoiser` needs), `metrics.jsonl` and `checkpoints/`.
  """
  data, num_tokens, dataset_id, tokens_meta = training_data(config)
  cfg = unet_config(config, num_tokens)
  total_steps = -(-len(data["q"]) // config.train.batch_size) * config.train.num_epochs
  _, init_fn, step_fn = init_and_step(config, cfg, total_steps)
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  atomic.write_json(workdir / "config.json", json.loads(config.to_json_best_effort()))
  atomic.write_json(workdir / "model.json", {"unet": dataclasses.asdict(cfg),
                                       "total_steps": total_steps})
  return loop.train(
      workdir=workdir, init_fn=init_fn, step_fn=step_fn, data=data,
      batch_size=config.train.batch_size, num_epochs=config.train.num_epochs, seed=config.seed,
      fingerprint=fingerprint(config, cfg, dataset_id, tokens_meta),
      checkpoint_every=config.train.checkpoint_every, keep=config.train.keep, desc="diffusion")


@dataclasses.dataclass(frozen=True)
class Denoiser:
  """A trained denoiser for inference.

  Attributes:
    graphdef: U-Net graph definition.
    params: the EMA parameters.
    unet: `UNetConfig`.
    config: the run's ConfigDict (sampling defaults, data and tokeniser dirs).
    fingerprint: what the checkpoint was trained on (dataset id, tokeniser).
  """

  graphdef: object
  params: dict
  unet: unet1d.UNetConfig
  config: ml_collections.ConfigDict
  fingerprint: dict


def load_denoiser(workdir: str | os.PathLike) -> Denoiser:
  """Restores the latest checkpoint of a `train_and_evaluate` run."""
  workdir = Path(workdir)
  try:
    config = ml_collections.ConfigDict(json.loads((workdir / "config.json").read_text()))
    model = json.loads((workdir / "model.json").read_text())
  except (OSError, ValueError) as e:
    raise FileNotFoundError(f"{workdir}: not a diffusion run directory ({e})") from e
  cfg = unet1d.UNetConfig(**{k: tuple(v) if isinstance(v, list) else v
                             for k, v in model["unet"].items()})
  graphdef, init_fn, _ = init_and_step(config, cfg, model["total_steps"])
  state, saved = loop.load_latest(workdir, init_fn)
  return Denoiser(graphdef=graphdef, params=state["ema_params"], unet=cfg, config=config,
                  fingerprint=saved)
