"""Training of the mixture density baseline (`cvmdx_jax.models.mdn`).

Loss: the negative log-likelihood of the true future under the mixture,
-log sum_k pi_k prod_{t, d} N(y_td; mu_ktd, sigma_ktd^2), divided by the 250 coordinates
of a trajectory (nats per coordinate). Optionally the first `loss.warmup_epochs` epochs
train as the multiple-choice MLP does (`train.baseline.wta_loss`: the winner's ADE and
the mode cross-entropy) plus the winner's Gaussian NLL with its mean held fixed (so the
stds learn too): a mixture NLL from the start can let one mode take every scenario while
the others never move (mode collapse); the winner-takes-all warm-up (MTP's best-mode
assignment) spreads the means first. On the demo data it was rejected on val: without it
the modes keep distinct shares and the val NLL is lower (configs/mdn.py).

Inputs, data loading, optimiser, train state, the val-chosen epoch (`select_metric`
"loss" = the val mixture NLL) and the run directory are the multiple-choice baseline's
(`cvmdx_jax.train.baseline`); the run is loaded with `inference.mdn_baseline.load_mdn`.
"""

import dataclasses
import os

import jax
import jax.numpy as jnp

from cvmdx_jax.config.mdn import MDNRunConfig, MixtureDensityConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.models import mdn
from cvmdx_jax.runs import fingerprints, layout
from cvmdx_jax.storage import locking
from cvmdx_jax.train import baseline, loop


def forward(graphdef, params, model_cfg: MixtureDensityConfig, inputs):
  """(means (B, K, T, 2) m, stds (B, K, T, 2) m, logits (B, K)) of a dict holding
  `train.baseline.INPUTS`."""
  return mdn.mixture(
      graphdef,
      params,
      model_cfg,
      inputs["q"],
      inputs["delta"],
      inputs["ego"],
      inputs["v0"],
      inputs["psi0"],
  )


def mdn_loss(means, stds, logits, future, weight, *, warm_up, cls_weight: float):
  """The training loss and its parts.

  Args:
    means, stds: (B, K, T, 2) m; logits: (B, K); future: (B, T, 2) m.
    weight: (B,) example weights (0 = padding).
    warm_up: bool scalar, True for the winner-takes-all warm-up loss.
    cls_weight: weight of the warm-up's cross-entropy.

  Returns:
    (loss, {"nll": mixture NLL per coordinate, "wta_ade": the winner's ADE m, "winner"
    (B,) int}): weighted means over the batch.
  """
  mean = lambda v: jnp.sum(weight * v) / jnp.maximum(jnp.sum(weight), 1.0)
  coords = future.shape[-2] * future.shape[-1]
  nll = mean(-mdn.log_likelihood(means, stds, logits, future)) / coords
  wta, parts = baseline.wta_loss(means, logits, future, weight, cls_weight)
  fixed = mdn.mode_log_densities(jax.lax.stop_gradient(means), stds, future)
  winner_nll = -jnp.take_along_axis(fixed, parts["winner"][:, None], axis=-1)[:, 0]
  warm = wta + mean(winner_nll) / coords
  return (
      jnp.where(warm_up, warm, nll),
      {"nll": nll, "wta_ade": parts["wta_ade"], "winner": parts["winner"]},
  )


def evaluate(graphdef, params, model_cfg, data) -> dict:
  """Read-outs on a whole split (dict of `INPUTS` + "future"): loss (mixture NLL per
  coordinate), nll (nats per scenario), wta_ade and the point read-outs of the means
  (`train.baseline.point_readouts`) in m, std_5s (m, the mean std of a coordinate at 5 s
  weighted by the mode probabilities) and head_share (K,) (share of scenarios whose
  closest mean, by ADE, is each mode)."""
  means, stds, logits = forward(graphdef, params, model_cfg, data)
  gt = data["future"]
  loss, parts = mdn_loss(means, stds, logits, gt, jnp.ones(len(gt)), warm_up=False, cls_weight=0.0)
  probs = jax.nn.softmax(logits, axis=-1)
  share = jnp.mean(jax.nn.one_hot(parts["winner"], model_cfg.num_hypotheses), axis=0)
  return {
      "loss": loss,
      "nll": loss * gt.shape[-2] * gt.shape[-1],
      "wta_ade": parts["wta_ade"],
      **baseline.point_readouts(means, logits, gt),
      "std_5s": jnp.mean(jnp.sum(probs * jnp.mean(stds[:, :, -1], axis=-1), axis=-1)),
      "head_share": share,
  }


def make_step_fn(graphdef, model_cfg, tx, config: MDNRunConfig, *, val: dict, steps_per_epoch: int):
  """The pure train step (`train.baseline.selecting_step_fn`): `mdn_loss` (the warm-up's
  for the first `config.loss.warmup_epochs` epochs), AdamW and the val-chosen epoch."""
  warmup_steps = config.loss.warmup_epochs * steps_per_epoch

  def loss_fn(params, batch, step):
    means, stds, logits = forward(graphdef, params, model_cfg, batch)
    loss, parts = mdn_loss(
        means,
        stds,
        logits,
        batch["future"],
        batch["weight"],
        warm_up=step < warmup_steps,
        cls_weight=config.loss.cls_weight,
    )
    return loss, {"nll": parts["nll"], "wta_ade": parts["wta_ade"]}

  return baseline.selecting_step_fn(
      tx,
      loss_fn,
      lambda params, data: evaluate(graphdef, params, model_cfg, data),
      val=val,
      steps_per_epoch=steps_per_epoch,
      select=config.train.select_metric,
  )


def fingerprint(config: MDNRunConfig, dataset_id: str, tokens_meta: dict) -> dict:
  """What a checkpoint belongs to: the baseline's fingerprint (`fingerprints.baseline`:
  model, features, optimiser, dataset, tokeniser checkpoint) plus the kind and the loss."""
  return {
      **fingerprints.baseline(config, dataset_id, tokens_meta),
      "kind": "mdn",
      "loss": dataclasses.asdict(config.loss),
  }


@locking.holds("workdir")
def train(config: MDNRunConfig, workdir: str | os.PathLike):
  """Trains the mixture density baseline into `workdir` (resuming if possible); returns
  the final state. `workdir` gets `config.json` (`config` with the tokens' Q),
  `metrics.jsonl` (train loss and the val curve per epoch) and `checkpoints/`."""
  data, meta = baseline.split_arrays(config, "train")
  val, _ = baseline.split_arrays(config, "val")
  dataset_id = dataset_lib.dataset_id(config.data_dir)
  config = config.with_tokens(int(meta["codebook_size"]))
  model_cfg = config.model
  steps_per_epoch = loop.steps_per_epoch(len(data["q"]), config.train.batch_size)
  tx = baseline.optimizer(config.train, steps_per_epoch * config.train.num_epochs)
  graphdef = mdn.make_graphdef(model_cfg)
  val_shapes = jax.eval_shape(
      lambda p: evaluate(graphdef, p, model_cfg, val),
      mdn.abstract_params(model_cfg),
  )

  return loop.train(
      workdir=workdir,
      init_fn=baseline.make_init_fn(model_cfg, tx, val_shapes, init=mdn.init),
      step_fn=make_step_fn(
          graphdef, model_cfg, tx, config, val=val, steps_per_epoch=steps_per_epoch
      ),
      data=data,
      fingerprint=fingerprint(config, dataset_id, meta),
      **loop.run_settings(config),
      epoch_end_fn=baseline.val_summary,
      on_start=lambda: layout.write_run_config(workdir, config),
      desc="mdn",
  )
