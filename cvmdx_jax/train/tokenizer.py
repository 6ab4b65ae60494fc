"""Training and inference of the scenario tokeniser (CVQ-VAE / VQ-VAE + maneuver head).

`train_and_evaluate(config, workdir)` trains on the "train" split with the shared loop
(`cvmdx_jax.train.loop`), logs per epoch the loss terms and, over the whole training
split, entries in use, perplexity and classifier accuracy; then fits the per-entry
Gaussians on the training latents and saves tokens q, latents z_hat and delta of every
split under `<workdir>/tokens/` (`cvmdx_jax.tokens`), plus `<workdir>/tokenizer.json`
(model settings, fingerprint) for `load_tokenizer`.

The train state is a plain pytree: {"step", "params" (pure dict of the NNX Params),
"opt_state", "usage" (Q,) running codebook usage}.
"""

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from flax import nnx

from cvmdx_jax import atomic, checkpointing, scenario_norm, tokens as tokens_lib, uncertainty
from cvmdx_jax.data import dataset as dataset_lib
from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.models import quantizer as quantizer_lib
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models.scenario_encoder import EncoderConfig
from cvmdx_jax.train import loop

CONFIG_NAME = "tokenizer.json"


def model_config(config: ml_collections.ConfigDict) -> tokenizer_lib.TokenizerConfig:
  """Static model settings from the run config (raises ValueError on bad values)."""
  return tokenizer_lib.TokenizerConfig(
      encoder=EncoderConfig(latent_dim=config.latent_dim, channels=tuple(config.channels),
                            kernel_size=config.kernel_size),
      quantizer=quantizer_lib.QuantizerConfig(
          kind=config.quantizer, codebook_size=config.codebook_size,
          latent_dim=config.latent_dim, beta=config.beta, usage_decay=config.usage_decay,
          revive_strength=config.revive_strength),
      cls_weight=config.cls_weight, ego_weight=config.ego_weight)


def _model_config_from_json(d: dict) -> tokenizer_lib.TokenizerConfig:
  enc = {**d["encoder"], "channels": tuple(d["encoder"]["channels"])}
  return tokenizer_lib.TokenizerConfig(EncoderConfig(**enc),
                                       quantizer_lib.QuantizerConfig(**d["quantizer"]),
                                       d["cls_weight"], d["ego_weight"])


def fingerprint(model_cfg: tokenizer_lib.TokenizerConfig, dataset_id: str) -> dict:
  """Identity of a tokeniser run, stored with its checkpoints and outputs."""
  return {"model": dataclasses.asdict(model_cfg), "dataset_id": dataset_id,
          "codebook_size": model_cfg.quantizer.codebook_size,
          "latent_dim": model_cfg.encoder.latent_dim,
          "xi_normalisation": {"offset": scenario_norm.XI_OFFSET.tolist(),
                               "scale": scenario_norm.XI_SCALE.tolist()}}


def make_graphdef(model_cfg: tokenizer_lib.TokenizerConfig) -> nnx.GraphDef:
  """The NNX graph definition of the tokeniser (no parameters are allocated)."""
  abstract = nnx.eval_shape(lambda: tokenizer_lib.Tokenizer(model_cfg, rngs=nnx.Rngs(0)))
  return nnx.split(abstract, nnx.Param)[0]


def make_init_fn(model_cfg, tx):
  """`init_fn(key) -> state` for the shared loop."""
  def init_fn(key):
    model = tokenizer_lib.Tokenizer(model_cfg, rngs=nnx.Rngs(params=key))
    params = nnx.to_pure_dict(nnx.split(model, nnx.Param)[1])
    return {"step": jnp.zeros((), jnp.int32), "params": params,
            "opt_state": tx.init(params), "usage": quantizer_lib.init_usage(model_cfg.quantizer)}
  return init_fn


def make_step_fn(graphdef, model_cfg, tx):
  """Pure `step_fn(state, batch, key) -> (state, metrics)` for the shared loop.

  One optimiser step on the tokeniser loss, then the quantiser's codebook update
  (running usage; for CVQ the anchor refresh, with anchors from this batch and `key`).
  """
  def step_fn(state, batch, key):
    def loss_of(params):
      return tokenizer_lib.loss_fn(nnx.merge(graphdef, params), batch, model_cfg)

    (loss, (metrics, out)), grads = jax.value_and_grad(loss_of, has_aux=True)(state["params"])
    updates, opt_state = tx.update(grads, state["opt_state"], state["params"])
    params = optax.apply_updates(state["params"], updates)
    codebook, usage = quantizer_lib.update_codebook(
        params["codebook"], state["usage"], out.z_hat, out.quantized.indices,
        batch["weight"].astype(jnp.float32), key, model_cfg.quantizer)
    _, perplexity = quantizer_lib.codebook_stats(
        out.quantized.indices, model_cfg.quantizer.codebook_size, batch["weight"])
    new_state = {"step": state["step"] + 1, "params": {**params, "codebook": codebook},
                 "opt_state": opt_state, "usage": usage}
    return new_state, {**metrics, "loss": loss, "grad_norm": optax.tree.norm(grads),
                       "batch_perplexity": perplexity}
  return step_fn


def optimizer(config: ml_collections.ConfigDict) -> optax.GradientTransformation:
  """Adam with global-norm clipping."""
  return optax.chain(optax.clip_by_global_norm(config.grad_clip),
                     optax.adam(config.learning_rate))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TokenizerBundle:
  """A trained tokeniser for inference (a pytree; graphdef and config are static).

  Attributes:
    params: pure dict of the model parameters.
    gaussians: the per-entry Gaussians for delta.
    graphdef: the NNX graph definition.
    config: the static model settings.
  """

  params: dict
  gaussians: uncertainty.Gaussians
  graphdef: nnx.GraphDef = dataclasses.field(metadata={"static": True})
  config: tokenizer_lib.TokenizerConfig = dataclasses.field(metadata={"static": True})


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
    model = nnx.merge(graphdef, params)
    z_hat = model.encode(x[0][None], x[1][None])[0]
    q = quantizer_lib.nearest(model.codebook[...], z_hat[None])[0]
    return z_hat, q, model.classifier(model.codebook[...][q])
  return jax.lax.map(one, (jnp.asarray(xi), jnp.asarray(mask)), batch_size=chunk)


_encode_jit = jax.jit(encode, static_argnums=(0, 4))


def tokenize(bundle: TokenizerBundle, xi: jax.Array, mask: jax.Array):
  """Tokens of B scenarios (jittable).

  Args:
    bundle: from `load_tokenizer`.
    xi: (B, 9, 75, 4) physical scenarios [x m, y m, v_x m/s, v_y m/s].
    mask: (B, 9, 75) bool.

  Returns:
    (q (B,) int32, z_hat (B, D) float32, delta (B,) float32).
  """
  model = nnx.merge(bundle.graphdef, bundle.params)
  z_hat = model.encode(xi, mask)
  q = quantizer_lib.nearest(model.codebook[...], z_hat)
  return q, z_hat, uncertainty.mahalanobis(z_hat, q, bundle.gaussians)


def _content_id(splits: dict[str, Scenarios]) -> str:
  digest = hashlib.sha1()
  for name in sorted(splits):
    for field in ("xi", "mask", "label"):
      digest.update(np.ascontiguousarray(getattr(splits[name], field)).tobytes())
  return f"content-sha1:{digest.hexdigest()[:16]}"


def _load_splits(config) -> tuple[dict[str, Scenarios], str]:
  names = config.splits or dataset_lib.split_names(config.data_dir)
  splits = {s: dataset_lib.load_split(config.data_dir, s) for s in names}
  return splits, dataset_lib.dataset_id(config.data_dir)


def _claim_workdir(workdir: Path, run: dict) -> None:
  """Writes <workdir>/tokenizer.json, or checks that an existing one has our fingerprint
  (so another Q / latent size / dataset is refused naming the differing keys)."""
  path = workdir / CONFIG_NAME
  if path.is_file():
    checkpointing.check_metadata(json.loads(path.read_text())["fingerprint"], run["fingerprint"],
                                 str(workdir))
  workdir.mkdir(parents=True, exist_ok=True)
  atomic.write_json(path, run, indent=1, sort_keys=True)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str | os.PathLike, *,
                       splits: dict[str, Scenarios] | None = None) -> dict:
  """Trains the tokeniser (or resumes / returns a finished run) and writes its outputs.

  Args:
    config: see configs/tokenizer.py.
    workdir: run directory (checkpoints, metrics.jsonl, tokenizer.json, tokens/).
    splits: scenarios per split name (must hold "train"); default: read
      `config.splits` (empty: every split) from `config.data_dir` with
      `cvmdx_jax.data.dataset`. Given splits are identified by a hash of their contents.

  Returns:
    The final train state.
  """
  model_cfg = model_config(config)
  if splits is None:
    splits, dataset_id = _load_splits(config)
  else:
    dataset_id = _content_id(splits)
  if "train" not in splits:
    raise ValueError(f"tokenizer: splits {sorted(splits)} lack 'train' (config.splits)")
  for name, s in splits.items():
    s.validate(source=f"{config.get('data_dir', '<given>')}/{name}")
  train = splits["train"]
  tx = optimizer(config)
  graphdef = make_graphdef(model_cfg)
  fp = fingerprint(model_cfg, dataset_id)
  _claim_workdir(Path(workdir), {"model": dataclasses.asdict(model_cfg), "fingerprint": fp,
                                 "optimizer_lr": config.learning_rate,
                                 "grad_clip": config.grad_clip})
  xi_train, mask_train = jnp.asarray(train.xi), jnp.asarray(train.mask)

  def epoch_end_fn(state, epoch):
    del epoch
    _, q, logits = _encode_jit(graphdef, state["params"], xi_train, mask_train,
                               config.encode_batch)
    in_use, perplexity = quantizer_lib.codebook_stats(q, model_cfg.quantizer.codebook_size)
    accuracy = jnp.mean(jnp.argmax(logits, -1) == jnp.asarray(train.label))
    return {"entries_in_use": in_use, "perplexity": perplexity, "train_accuracy": accuracy}

  state = loop.train(
      workdir=workdir, init_fn=make_init_fn(model_cfg, tx),
      step_fn=make_step_fn(graphdef, model_cfg, tx),
      data={"xi": train.xi, "mask": train.mask, "label": train.label},
      batch_size=config.batch_size, num_epochs=config.num_epochs, seed=config.seed,
      fingerprint=fp, checkpoint_every=config.checkpoint_every, keep=config.keep,
      epoch_end_fn=epoch_end_fn, desc=f"tokenizer {model_cfg.quantizer.kind}")

  workdir = Path(workdir)
  meta = {"dataset_id": dataset_id, "data_dir": str(config.get("data_dir", "")),
          "codebook_size": model_cfg.quantizer.codebook_size,
          "latent_dim": model_cfg.encoder.latent_dim, "quantizer": model_cfg.quantizer.kind,
          "checkpoint": {"workdir": str(workdir.resolve()), "step": int(state["step"]),
                         "fingerprint": fp}}
  encoded = {name: _encode_jit(graphdef, state["params"], jnp.asarray(s.xi),
                               jnp.asarray(s.mask), config.encode_batch)
             for name, s in splits.items()}
  z_train, q_train, _ = encoded["train"]
  gaussians = uncertainty.fit_gaussians(z_train, q_train, state["params"]["codebook"],
                                        shrinkage=config.shrinkage, ridge=config.ridge)
  tokens_lib.save_gaussians(workdir / "tokens" / f"{tokens_lib.GAUSSIANS_NAME}.npz",
                            gaussians, meta)
  for name, (z_hat, q, _) in encoded.items():
    delta = uncertainty.mahalanobis(z_hat, q, gaussians)
    tokens_lib.save_tokens(tokens_lib.tokens_path(workdir, name),
                           tokens_lib.Tokens(np.asarray(q), np.asarray(z_hat), np.asarray(delta)),
                           {**meta, "split": name})
  return state


def load_tokenizer(workdir: str | os.PathLike) -> TokenizerBundle:
  """The trained tokeniser of `workdir` for inference.

  Raises:
    FileNotFoundError: the workdir holds no tokeniser run (no tokenizer.json) or its
      outputs are missing (the run has not finished).
    CheckpointMismatchError: the checkpoint does not match the run's settings.
    tokens.TokensMismatchError: the saved Gaussians belong to another checkpoint.
  """
  workdir = Path(workdir)
  path = workdir / CONFIG_NAME
  if not path.is_file():
    raise FileNotFoundError(f"{path}: missing; train the tokeniser with this workdir first")
  saved = json.loads(path.read_text())
  model_cfg = _model_config_from_json(saved["model"])
  init_fn = make_init_fn(model_cfg, optax.chain(optax.clip_by_global_norm(saved["grad_clip"]),
                                                optax.adam(saved["optimizer_lr"])))
  state, _ = loop.load_latest(workdir, init_fn, saved["fingerprint"])
  gpath = workdir / "tokens" / f"{tokens_lib.GAUSSIANS_NAME}.npz"
  gaussians, gmeta = tokens_lib.load_gaussians(gpath)
  if gmeta["checkpoint"]["step"] != int(state["step"]):
    raise tokens_lib.TokensMismatchError(
        f"{gpath}: Gaussians fitted at step {gmeta['checkpoint']['step']}, the checkpoint "
        f"is at step {int(state['step'])}; rerun train_and_evaluate")
  gaussians = jax.tree.map(jnp.asarray, gaussians)
  return TokenizerBundle(state["params"], gaussians, make_graphdef(model_cfg), model_cfg)
