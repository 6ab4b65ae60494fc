"""Training of the scenario tokeniser (CVQ-VAE / VQ-VAE + maneuver head).

`train(config, workdir)` trains on the "train" split with the shared loop
(`cvmdx_jax.train.loop`), logging per epoch the loss terms and, over the whole training
split, entries in use, perplexity and classifier accuracy; then `export_tokens` fits the
per-entry Gaussians on the training latents and saves tokens q, latents z_hat and delta of
every split under `<workdir>/tokens/` (`runs.tokens`). `<workdir>/tokenizer.json` (model
settings, fingerprint) is for `inference.bundles.load_tokenizer`.

The train state is a plain pytree: {"step", "params" (pure dict of the NNX Params),
"opt_state", "usage" (Q,) running codebook usage}.
"""

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from cvmdx_jax import sharding
from cvmdx_jax.config.runs import TokenizerRunConfig
from cvmdx_jax.config.train import TokenizerTrainConfig
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.errors import UserError
from cvmdx_jax.models import quantizer as quantizer_lib
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models import uncertainty
from cvmdx_jax.runs import fingerprints, layout
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage import identity, locking
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.storage.identity import content_id
from cvmdx_jax.train import loop


def make_init_fn(model_cfg, tx):
  """`init_fn(key) -> state` for the shared loop."""

  def init_fn(key):
    _, params = tokenizer_lib.init_tokenizer(model_cfg, key)
    return {
        "step": jnp.zeros((), jnp.int32),
        "params": params,
        "opt_state": tx.init(params),
        "usage": quantizer_lib.init_usage(model_cfg.quantizer),
    }

  return init_fn


def make_step_fn(graphdef, model_cfg, tx):
  """Pure `step_fn(state, batch, key) -> (state, metrics)` for the shared loop.

  One optimiser step on the tokeniser loss, then the quantiser's codebook update
  (running usage; for CVQ the anchor refresh, with anchors from this batch and `key`).
  """

  def step_fn(state, batch, key):
    def loss_of(params):
      return tokenizer_lib.loss_fn(graphdef, params, batch, model_cfg)

    (loss, (metrics, out)), grads = jax.value_and_grad(loss_of, has_aux=True)(state["params"])
    updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    codebook, usage = quantizer_lib.update_codebook(
        params["codebook"],
        state["usage"],
        out.z_hat,
        out.quantized.indices,
        batch["weight"].astype(jnp.float32),
        key,
        model_cfg.quantizer,
    )
    _, perplexity = quantizer_lib.codebook_stats(
        out.quantized.indices, model_cfg.quantizer.codebook_size, batch["weight"]
    )
    new_state = {
        "step": state["step"] + 1,
        "params": {**params, "codebook": codebook},
        "opt_state": opt_state,
        "usage": usage,
    }
    return new_state, {
        **metrics,
        "loss": loss,
        "grad_norm": optax.tree.norm(grads),
        "batch_perplexity": perplexity,
    }

  return step_fn


def optimizer(t: TokenizerTrainConfig) -> optax.GradientTransformation:
  """Adam with global-norm clipping."""
  return optax.chain(optax.clip_by_global_norm(t.grad_clip), optax.adam(t.learning_rate))


def encode(graphdef, params, xi, mask, chunk: int = 512):
  """Latents, tokens and maneuver logits of many scenarios, `chunk` at a time.

  Args:
    graphdef, params: the tokeniser.
    xi: (M, 9, 75, 4) physical scenarios; mask: (M, 9, 75).
    chunk: scenarios per `lax.map` batch.

  Returns:
    (z_hat (M, D), q (M,) int32, logits (M, 3)).
  """

  def one(x):
    z_hat, q = tokenizer_lib.encode(graphdef, params, x[0][None], x[1][None])
    return z_hat[0], q[0], tokenizer_lib.classify(graphdef, params, q[0])

  return jax.lax.map(one, (jnp.asarray(xi), jnp.asarray(mask)), batch_size=chunk)


_encode_jit = jax.jit(encode, static_argnums=(0, 4))


def _content_id(splits: dict[str, Scenarios]) -> str:
  return content_id(
      {name: {f: getattr(s, f) for f in ("xi", "mask", "label")} for name, s in splits.items()}
  )


def _load_splits(config: TokenizerRunConfig) -> tuple[dict[str, Scenarios], str]:
  names = config.splits or dataset_lib.split_names(config.data_dir)
  splits = {s: dataset_lib.load_split(config.data_dir, s) for s in names}
  return splits, dataset_lib.dataset_id(config.data_dir)


@locking.holds("workdir")
def train(
    config: TokenizerRunConfig,
    workdir: str | os.PathLike,
    *,
    splits: dict[str, Scenarios] | None = None,
) -> dict:
  """Trains the tokeniser (or resumes / returns a finished run), then exports its tokens.

  Args:
    config: the run (`TokenizerRunConfig.from_config` of configs/tokenizer.py).
    workdir: run directory (checkpoints, metrics.jsonl, tokenizer.json, tokens/).
    splits: scenarios per split name (must hold "train"); default: read
      `config.splits` (empty: every split) from `config.data_dir` with
      `cvmdx_jax.data.dataset`. Given splits are identified by a hash of their contents.

  Returns:
    The final train state.
  """
  model_cfg = config.model
  if splits is None:
    splits, dataset_id = _load_splits(config)
  else:
    dataset_id = _content_id(splits)
  if "train" not in splits:
    raise UserError(f"tokenizer: splits {sorted(splits)} lack 'train' (config.splits)")
  for name, s in splits.items():
    s.validate(source=f"{config.data_dir}/{name}")
  train_split = splits["train"]
  tx = optimizer(config.train)
  graphdef = tokenizer_lib.make_graphdef(model_cfg)
  fp = fingerprints.tokenizer(model_cfg, dataset_id)
  saved = layout.saved_tokenizer_fingerprint(workdir)
  if saved is not None:
    identity.check(saved, fp, f"tokeniser run {workdir}", CheckpointMismatchError)
  xi_train, mask_train = jnp.asarray(train_split.xi), jnp.asarray(train_split.mask)

  def epoch_end_fn(state, epoch):
    del epoch
    _, q, logits = _encode_jit(graphdef, state["params"], xi_train, mask_train, config.encode_batch)
    in_use, perplexity = quantizer_lib.codebook_stats(q, model_cfg.quantizer.codebook_size)
    accuracy = jnp.mean(jnp.argmax(logits, -1) == jnp.asarray(train_split.label))
    return {"entries_in_use": in_use, "perplexity": perplexity, "train_accuracy": accuracy}

  state = loop.train(
      workdir=workdir,
      init_fn=make_init_fn(model_cfg, tx),
      step_fn=make_step_fn(graphdef, model_cfg, tx),
      data={"xi": train_split.xi, "mask": train_split.mask, "label": train_split.label},
      fingerprint=fp,
      **loop.run_settings(config),
      epoch_end_fn=epoch_end_fn,
      desc=f"tokenizer {model_cfg.quantizer.kind}",
      on_start=lambda: layout.write_tokenizer_dir(workdir, model_cfg, fp),
  )
  if sharding.is_primary():  # process 0 writes the tokens of a multi-process run
    export_tokens(config, workdir, state, splits, dataset_id, fp)
  return state


def export_tokens(
    config: TokenizerRunConfig,
    workdir: str | os.PathLike,
    state: dict,
    splits: dict[str, Scenarios],
    dataset_id: str,
    fingerprint: dict,
) -> None:
  """Fits the per-entry Gaussians on the train split's latents of the trained `state` and
  writes them and the tokens (q, z_hat, delta) of every split under `<workdir>/tokens/`,
  each with the metadata of the checkpoint that made them (dataset id, step, params id)."""
  model_cfg = config.model
  graphdef = tokenizer_lib.make_graphdef(model_cfg)
  workdir = Path(workdir)
  meta = {
      "dataset_id": dataset_id,
      "data_dir": config.data_dir,
      "codebook_size": model_cfg.quantizer.codebook_size,
      "latent_dim": model_cfg.encoder.latent_dim,
      "quantizer": model_cfg.quantizer.kind,
      "checkpoint": {
          "workdir": str(workdir.resolve()),
          "step": int(state["step"]),
          "fingerprint": fingerprint,
          "params_id": content_id(state["params"]),
      },
  }
  encoded = {
      name: _encode_jit(
          graphdef, state["params"], jnp.asarray(s.xi), jnp.asarray(s.mask), config.encode_batch
      )
      for name, s in splits.items()
  }
  z_train, q_train, _ = encoded["train"]
  gaussians = uncertainty.fit_gaussians(
      z_train,
      q_train,
      state["params"]["codebook"],
      shrinkage=config.uncertainty.shrinkage,
      ridge=config.uncertainty.ridge,
  )
  tokens_lib.save_gaussians(tokens_lib.gaussians_path(workdir), gaussians, meta)
  for name, (z_hat, q, _) in encoded.items():
    delta = uncertainty.mahalanobis(z_hat, q, gaussians)
    tokens_lib.save_tokens(
        tokens_lib.tokens_path(workdir, name),
        tokens_lib.Tokens(np.asarray(q), np.asarray(z_hat), np.asarray(delta)),
        {**meta, "split": name},
    )
