"""Training of the motion diffusion model v_theta(x_t, t, q) on the shared loop.

Targets: normalised controls x0 = clip([a_x / 4, yaw_rate / 0.7], -1, 1), (M, 125, 2)
(with an `ego_*residual` conditioning: of controls minus the ego's extrapolated current
controls); condition: the tokeniser's token q of each training scenario (and, with an
`ego_film*` conditioning, its ego-motion features, `cvmdx_jax.ego_motion`). Loss: the
v-loss with conditioning dropout (of the token only) to the null token Q; with
`diffusion.intent_conditioning` the features end in the one-hot true maneuver class and the
loss adds the cross-entropy of that class under the U-Net's intent classifier on the ego
features (its own parameters: the sum trains both at once). Optimiser:
AdamW with linear warm-up and cosine decay to `min_lr`, global-norm clipping; an EMA of
the weights (with the usual warm-up of the decay, min(decay, (1 + step) / (10 + step))) is
what inference uses.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cvmdx_jax import ego_motion, targets
from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.train import DiffusionTrainConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.diffusion import cosine_schedule, losses, v_loss
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import fingerprints, layout
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage import locking
from cvmdx_jax.train import loop, optimizers


def optimizer(t: DiffusionTrainConfig, total_steps: int):
  """AdamW with linear warm-up, cosine decay to `t.min_lr` and global-norm clipping."""
  return optimizers.adamw(t, total_steps, t.min_lr)


def make_init_fn(cfg: UNetConfig, tx):
  """init_fn(key) -> {params, ema_params, opt_state, step}."""

  def init_fn(key):
    _, params = unet1d.init_unet(cfg, key)
    # a copy, so that donating the state never donates one buffer twice
    return {
        "params": params,
        "ema_params": jax.tree.map(jnp.copy, params),
        "opt_state": tx.init(params),
        "step": jnp.zeros((), jnp.int32),
    }

  return init_fn


def make_step_fn(
    graphdef, cfg: UNetConfig, tx, *, cond_drop_prob: float, ema_decay: float, num_steps: int
):
  """The pure train step of the shared loop: v-loss (+ the intent classifier's
  cross-entropy where `cfg.num_intents`, reported as "intent_ce"; `batch["label"]` then
  holds the classes), AdamW update, EMA."""
  schedule = cosine_schedule(num_steps)

  def step_fn(state, batch, key):
    k_loss, k_drop = jax.random.split(key)
    weight = batch["weight"] * batch.get("class_weight", 1.0)

    def loss_fn(params):
      ego = batch["ego"] if cfg.cond_dim else None
      model = lambda x_t, t, q: unet1d.apply_unet(graphdef, params, x_t, t, q, k_drop, ego)
      loss = v_loss(
          model,
          batch["x0"],
          batch["q"],
          k_loss,
          schedule,
          null_cond=cfg.null_token,
          cond_drop_prob=cond_drop_prob,
          weight=weight,
      )
      if not cfg.num_intents:
        return loss, {}
      logits = unet1d.apply_intent(graphdef, params, ego[:, : cfg.intent_features])
      ce = intent_cross_entropy(logits, batch["label"], weight)
      return loss + ce, {"intent_ce": ce}

    (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state["params"])
    return apply_gradients(state, grads, tx, ema_decay), {
        "loss": loss,
        "grad_norm": optax.tree.norm(grads),
        **aux,
    }

  return step_fn


def intent_cross_entropy(logits, label, weight):
  """The weighted mean over examples of -log softmax(logits)[label]; logits (B, C),
  label (B,) int, weight (B,) (0 for padding rows)."""
  return losses.weighted_mean(
      optax.softmax_cross_entropy_with_integer_labels(logits, label), weight
  )


def apply_gradients(state, grads, tx, ema_decay: float):
  """`state` ({params, ema_params, opt_state, step, ...}) after one optimiser update with
  `grads` and the EMA with its warm-up, min(ema_decay, (1 + step) / (10 + step)); other
  entries pass through."""
  updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
  params = optax.apply_updates(state["params"], updates)
  step = state["step"] + 1
  decay = jnp.minimum(ema_decay, (1.0 + step) / (10.0 + step))
  ema = jax.tree.map(lambda e, p: decay * e + (1.0 - decay) * p, state["ema_params"], params)
  return {**state, "params": params, "ema_params": ema, "opt_state": opt_state, "step": step}


def training_data(
    config: DiffusionRunConfig, *, delta: bool = False
) -> tuple[dict, int, str, dict]:
  """(arrays {x0, q[, ego][, class_weight][, label][, delta]}, Q, dataset id, tokens
  metadata) of the training split; `class_weight` (M,) only where `diffusion.class_weights`
  is not all 1; `label` (M,) the maneuver classes of an intent conditioning (whose `ego`
  then ends in their one-hot); `delta` (M,), the tokens' uncertainty, where asked for
  (distillation)."""
  d = config.diffusion
  scenarios = dataset_lib.load_split(config.data_dir, "train")
  dataset_id = dataset_lib.dataset_id(config.data_dir)
  toks, meta = tokens_lib.load_tokens(
      tokens_lib.tokens_path(config.tokenizer_dir, "train"),
      dataset_id=dataset_id,
      num_scenarios=len(scenarios),
  )
  data, controls = {"q": toks.q.astype(np.int32)}, scenarios.controls
  if delta:
    data["delta"] = np.asarray(toks.delta, np.float32)
  if d.conditioning != "token":
    data["ego"] = np.asarray(ego_motion.ego_features(scenarios.xi, scenarios.mask))
    if ego_motion.uses_residual(d.conditioning):
      controls = controls - ego_motion.residual_controls(data["ego"], d.residual_decay_s)
  data["x0"] = np.asarray(targets.normalize_controls(controls, d.control_scale), np.float32)
  if d.weighted_classes:
    data["class_weight"] = np.asarray(d.class_weights, np.float32)[scenarios.label]
  if d.intent_conditioning:
    data["label"] = np.asarray(scenarios.label, np.int32)
    data["ego"] = np.concatenate(
        [data["ego"], np.eye(d.num_intents, dtype=np.float32)[data["label"]]], axis=-1
    )
  return data, int(meta["codebook_size"]), dataset_id, meta


def init_and_step(config: DiffusionRunConfig, total_steps: int):
  """(graphdef, init_fn, step_fn) of a run (`config.model` sized for its tokens) with
  `total_steps` optimiser steps."""
  cfg = config.model
  graphdef = unet1d.make_graphdef(cfg)
  tx = optimizer(config.train, total_steps)
  step_fn = make_step_fn(
      graphdef,
      cfg,
      tx,
      cond_drop_prob=config.diffusion.cond_drop_prob,
      ema_decay=config.train.ema_decay,
      num_steps=config.diffusion.num_steps,
  )
  return graphdef, make_init_fn(cfg, tx), step_fn


@locking.holds("workdir")
def train(config: DiffusionRunConfig, workdir: str | os.PathLike):
  """Trains the denoiser into `workdir` (resuming if possible); returns the final state.

  `workdir` gets `config.json` (`config` with the tokens' Q), `metrics.jsonl` and
  `checkpoints/` (`inference.bundles.load_denoiser` reads them for inference).
  """
  data, num_tokens, dataset_id, tokens_meta = training_data(config)
  config = config.with_tokens(num_tokens)
  total_steps = (
      loop.steps_per_epoch(len(data["q"]), config.train.batch_size) * config.train.num_epochs
  )
  _, init_fn, step_fn = init_and_step(config, total_steps)
  return loop.train(
      workdir=workdir,
      init_fn=init_fn,
      step_fn=step_fn,
      data=data,
      fingerprint=fingerprints.diffusion(config, dataset_id, tokens_meta),
      **loop.run_settings(config),
      on_start=lambda: layout.write_run_config(workdir, config),
      desc="diffusion",
  )
