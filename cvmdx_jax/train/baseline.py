"""Training of the multiple-choice MLP baseline (`cvmdx_jax.models.multiple_choice`).

Loss (winner-takes-all with mode classification): per training scenario, the head whose
trajectory is closest to the truth by ADE wins; the loss is that head's ADE (m) plus
`cls_weight` times the cross-entropy of the K mode logits against the winner's index.
No other head's trajectory gets a gradient from that scenario. Optimiser: AdamW with
linear warm-up and cosine decay, global-norm clipping.

The epoch is chosen on val: at the last step of every epoch the step evaluates the loss
and the read-outs of `evaluate` on the whole val split (its features, tokens and futures
are constants of the jitted step) and keeps, in the train state (`best`), the parameters
of the epoch with the lowest val `train.select_metric` (default minADE_K: the
cross-entropy part of the loss is measured against winners that move as the heads move,
and on the demo data it made the val loss pick an early, worse epoch; BUILD_NOTES.md), so
the choice is checkpointed, resumed and bit-identical like the rest of the state.
`metrics.jsonl` holds the val curve (`val_*` per epoch); the run directory is laid out
in `runs.layout` and loaded with `inference.bundles.load_baseline`.

Train state: {"params", "opt_state", "step", "val" (the last val read-outs), "best"
{"params", "val_score", "epoch"}}.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cvmdx_jax import constants, ego_motion
from cvmdx_jax.config.models import MultipleChoiceConfig
from cvmdx_jax.config.runs import BaselineRunConfig
from cvmdx_jax.config.train import BaselineTrainConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.evaluation import metrics
from cvmdx_jax.models import multiple_choice as mc
from cvmdx_jax.runs import fingerprints, layout
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage import locking
from cvmdx_jax.train import loop, optimizers

INPUTS = ("q", "delta", "ego", "v0", "psi0")  # what a forward pass reads
_EPS_M2 = 1e-6  # m^2 under the square root of a displacement (its gradient at 0)


def wta_loss(trajectories, logits, future, weight, cls_weight: float):
  """Winner-takes-all loss and its parts.

  Args:
    trajectories: (B, K, T, 2) hypotheses, m; logits: (B, K) mode logits.
    future: (B, T, 2) ground truth, m; weight: (B,) example weights (0 = padding).
    cls_weight: weight of the cross-entropy term.

  Returns:
    (loss, {"wta_ade", "cross_entropy", "winner" (B,) int}): weighted means over the
    batch; `winner` = argmin_k ADE_k.
  """
  err = jnp.sqrt(jnp.sum((trajectories - future[:, None]) ** 2, axis=-1) + _EPS_M2)
  ade = jnp.mean(err, axis=-1)  # (B, K)
  winner = jnp.argmin(ade, axis=-1)
  regression = jnp.take_along_axis(ade, winner[:, None], axis=-1)[:, 0]
  ce = -jnp.take_along_axis(jax.nn.log_softmax(logits), winner[:, None], axis=-1)[:, 0]
  mean = lambda v: jnp.sum(weight * v) / jnp.maximum(jnp.sum(weight), 1.0)
  return (
      mean(regression + cls_weight * ce),
      {"wta_ade": mean(regression), "cross_entropy": mean(ce), "winner": winner},
  )


def forward(graphdef, params, model_cfg: MultipleChoiceConfig, inputs):
  """(trajectories (B, K, T, 2), logits (B, K)) of a dict holding `INPUTS`."""
  controls, logits = mc.apply(graphdef, params, inputs["q"], inputs["delta"], inputs["ego"])
  return mc.rollout(model_cfg, controls, inputs["ego"], inputs["v0"], inputs["psi0"]), logits


def evaluate(graphdef, params, model_cfg, data, cls_weight: float) -> dict:
  """Loss and read-outs on a whole split (dict of `INPUTS` + "future"): loss, wta_ade,
  cross_entropy, min_ade / min_fde (best of K), ml_ade / ml_fde (most likely), mean_ade /
  mean_fde (probability-weighted mean) in m, head_share (K,) share of scenarios each
  head wins."""
  trajectories, logits = forward(graphdef, params, model_cfg, data)
  gt = data["future"]
  loss, parts = wta_loss(trajectories, logits, gt, jnp.ones(len(gt)), cls_weight)
  share = jnp.mean(jax.nn.one_hot(parts.pop("winner"), model_cfg.num_hypotheses), axis=0)
  return {"loss": loss, **parts, **point_readouts(trajectories, logits, gt), "head_share": share}


def point_readouts(trajectories, logits, gt) -> dict:
  """Split means (m) of min_ade / min_fde (best of K), ml_ade / ml_fde (most likely) and
  mean_ade / mean_fde (probability-weighted mean) of trajectories (B, K, T, 2) with
  probabilities softmax(logits (B, K)) against gt (B, T, 2)."""
  probs = jax.nn.softmax(logits, axis=-1)
  valid = jnp.ones(probs.shape, bool)
  likely = metrics.most_likely(trajectories, probs)
  mean = jnp.einsum("bk,bktc->btc", probs, trajectories, precision=constants.EXACT_MATMUL)
  return {
      "min_ade": jnp.mean(metrics.min_ade_k(trajectories, gt, valid)),
      "min_fde": jnp.mean(metrics.min_fde_k(trajectories, gt, valid)),
      "ml_ade": jnp.mean(metrics.ade(likely, gt)),
      "ml_fde": jnp.mean(metrics.fde(likely, gt)),
      "mean_ade": jnp.mean(metrics.ade(mean, gt)),
      "mean_fde": jnp.mean(metrics.fde(mean, gt)),
  }


def optimizer(t: BaselineTrainConfig, total_steps: int):
  """AdamW with linear warm-up, cosine decay to `t.end_lr_fraction` of the peak and
  global-norm clipping."""
  return optimizers.adamw(t, total_steps, t.learning_rate * t.end_lr_fraction)


def make_init_fn(model_cfg, tx, val_metrics, init=mc.init):
  """init_fn(key) -> train state of the model `init(model_cfg, key)`; `val_metrics` gives
  the structure of `state["val"]`."""

  def init_fn(key):
    _, params = init(model_cfg, key)
    # copies, so that donating the state never donates one buffer twice
    best = {
        "params": jax.tree.map(jnp.copy, params),
        "val_score": jnp.asarray(jnp.inf, jnp.float32),
        "epoch": jnp.zeros((), jnp.int32),
    }
    val = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), val_metrics)
    return {
        "params": params,
        "opt_state": tx.init(params),
        "step": jnp.zeros((), jnp.int32),
        "val": val,
        "best": best,
    }

  return init_fn


def make_step_fn(
    graphdef, model_cfg, tx, *, cls_weight: float, val: dict, steps_per_epoch: int, select: str
):
  """The pure train step of the shared loop: WTA loss, AdamW update and, at the last
  step of each epoch, the val evaluation (`evaluate`) and the choice of the epoch with
  the lowest val `select` (one of `config.runs.SELECT_METRICS`)."""

  def loss_fn(params, batch, step):
    del step
    trajectories, logits = forward(graphdef, params, model_cfg, batch)
    loss, parts = wta_loss(trajectories, logits, batch["future"], batch["weight"], cls_weight)
    return loss, {"wta_ade": parts["wta_ade"], "cross_entropy": parts["cross_entropy"]}

  return selecting_step_fn(
      tx,
      loss_fn,
      lambda params, data: evaluate(graphdef, params, model_cfg, data, cls_weight),
      val=val,
      steps_per_epoch=steps_per_epoch,
      select=select,
  )


def selecting_step_fn(tx, loss_fn, evaluate_fn, *, val: dict, steps_per_epoch: int, select: str):
  """A pure train step of the shared loop: `loss_fn(params, batch, step) -> (loss, {name:
  scalar})`, the optimiser `tx` and, at the last step of each epoch, `evaluate_fn(params,
  val) -> {name: value}` and the choice of the epoch with the lowest val `select`."""
  val = jax.tree.map(jnp.asarray, val)

  def step_fn(state, batch, key):
    del key  # the step is deterministic given the batch
    (loss, parts), grads = jax.value_and_grad(
        lambda p: loss_fn(p, batch, state["step"]), has_aux=True
    )(state["params"])
    updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    step = state["step"] + 1

    def choose(_):
      scores = evaluate_fn(params, val)
      this = {"params": params, "val_score": scores[select], "epoch": step // steps_per_epoch}
      better = scores[select] < state["best"]["val_score"]
      return scores, jax.tree.map(lambda n, o: jnp.where(better, n, o), this, state["best"])

    scores, best = jax.lax.cond(
        step % steps_per_epoch == 0, choose, lambda _: (state["val"], state["best"]), None
    )
    new = {"params": params, "opt_state": opt_state, "step": step, "val": scores, "best": best}
    return new, {"loss": loss, **parts, "grad_norm": optax.tree.norm(grads)}

  return step_fn


def split_arrays(config: BaselineRunConfig, split: str) -> tuple[dict, dict]:
  """({q, delta, ego, v0, psi0, future} numpy arrays of `split`, its tokens' metadata)."""
  scenarios = dataset_lib.load_split(config.data_dir, split)
  toks, meta = tokens_lib.load_tokens(
      tokens_lib.tokens_path(config.tokenizer_dir, split),
      dataset_id=dataset_lib.dataset_id(config.data_dir),
      num_scenarios=len(scenarios),
  )
  arrays = {
      "q": toks.q.astype(np.int32),
      "delta": toks.delta.astype(np.float32),
      "ego": np.asarray(ego_motion.ego_features(scenarios.xi, scenarios.mask)),
      "v0": scenarios.v0.astype(np.float32),
      "psi0": scenarios.psi0.astype(np.float32),
      "future": scenarios.future.astype(np.float32),
  }
  return arrays, meta


@locking.holds("workdir")
def train(config: BaselineRunConfig, workdir: str | os.PathLike):
  """Trains the baseline into `workdir` (resuming if possible); returns the final state.

  `workdir` gets `config.json` (`config` with the tokens' Q), `metrics.jsonl` (train loss
  and the val curve per epoch) and `checkpoints/` (`runs.layout`).
  """
  data, meta = split_arrays(config, "train")
  val, _ = split_arrays(config, "val")
  dataset_id = dataset_lib.dataset_id(config.data_dir)
  config = config.with_tokens(int(meta["codebook_size"]))
  model_cfg = config.model
  steps_per_epoch = loop.steps_per_epoch(len(data["q"]), config.train.batch_size)
  tx = optimizer(config.train, steps_per_epoch * config.train.num_epochs)
  graphdef = mc.make_graphdef(model_cfg)
  cls_weight = config.loss.cls_weight
  val_shapes = jax.eval_shape(
      lambda p: evaluate(graphdef, p, model_cfg, val, cls_weight),
      mc.abstract_params(model_cfg),
  )

  return loop.train(
      workdir=workdir,
      init_fn=make_init_fn(model_cfg, tx, val_shapes),
      step_fn=make_step_fn(
          graphdef,
          model_cfg,
          tx,
          cls_weight=cls_weight,
          val=val,
          steps_per_epoch=steps_per_epoch,
          select=config.train.select_metric,
      ),
      data=data,
      fingerprint=fingerprints.baseline(config, dataset_id, meta),
      **loop.run_settings(config),
      epoch_end_fn=val_summary,
      on_start=lambda: layout.write_run_config(workdir, config),
      desc="baseline",
  )


def val_summary(state, epoch) -> dict:
  """The metrics line's val part (`loop.train`'s `epoch_end_fn`): the last val read-outs
  as `val_<name>`, the chosen epoch and its val score."""
  del epoch
  return {
      **{f"val_{k}": v for k, v in state["val"].items()},
      "best_epoch": state["best"]["epoch"],
      "best_val_score": state["best"]["val_score"],
  }
