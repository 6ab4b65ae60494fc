"""Run directories: their file names, fingerprints, writers, and the inference loaders.

A tokeniser run (`cvmdx_jax.train.tokenizer`):

    <dir>/tokenizer.json         {"model": TokenizerConfig fields, "fingerprint": ...}
    <dir>/checkpoints/<epoch>/   train state {"step", "params", "opt_state", "usage"}
    <dir>/metrics.jsonl          one JSON line per epoch
    <dir>/tokens/                tokens per split and the per-entry Gaussians (`tokens`)

A diffusion run (`cvmdx_jax.train.diffusion`):

    <dir>/config.json            the run's ConfigDict (sampling defaults, data, tokeniser)
    <dir>/model.json             {"unet": UNetConfig fields}
    <dir>/checkpoints/<epoch>/   train state {"step", "params", "ema_params", "opt_state"}
    <dir>/metrics.jsonl

Integrity: tokenizer.json, config.json, model.json and tokens/*.npz are checksummed
(`cvmdx_jax.checksums`, a checksums.json per directory) and checkpoints carry the sha256
of every leaf (`cvmdx_jax.checkpointing`); the loaders verify both and raise
`CorruptRunError` / `CheckpointMismatchError` naming the file. The trainers check a
resumed directory (`check_tokenizer_dir`, the checkpoint's fingerprint) before they write
anything into it (`write_tokenizer_dir`, `write_diffusion_dir`). A denoiser's fingerprint
records the tokeniser checkpoint it was trained on (fingerprint, step and
`params_sha256`, the `checkpointing.tree_digest` of the tokeniser's parameters).

`load_tokenizer` and `load_denoiser` restore only what inference needs (the tokeniser's
parameters and step, the denoiser's EMA parameters) into an abstract tree built from the
saved model config: no optimiser and no trainer code is involved (this module imports
nothing from `cvmdx_jax.train`). Diffusion runs written before parameters were pure
dicts (leaves `<path>/value`) still load.
"""

import dataclasses
import json
import math
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx

from cvmdx_jax import constants, ego_motion, sharding, tokens
from cvmdx_jax.storage import checkpointing, checksums
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.storage.checksums import CorruptRunError
from cvmdx_jax.config_dataclass import to_dataclass
from cvmdx_jax.inference.sampling import SamplingConfig
from cvmdx_jax.models import scenario_norm, unet1d, uncertainty
from cvmdx_jax.models import tokenizer as tokenizer_lib

CHECKPOINTS = "checkpoints"  # orbax step directories (`cvmdx_jax.checkpointing`)
METRICS = "metrics.jsonl"
TOKENIZER_JSON = "tokenizer.json"
CONFIG_JSON = "config.json"
MODEL_JSON = "model.json"


def tokenizer_fingerprint(model_cfg: tokenizer_lib.TokenizerConfig, dataset_id: str) -> dict:
  """Identity of a tokeniser run, stored with its checkpoints and outputs."""
  return {"model": dataclasses.asdict(model_cfg), "dataset_id": dataset_id,
          "codebook_size": model_cfg.quantizer.codebook_size,
          "latent_dim": model_cfg.encoder.latent_dim,
          "xi_normalisation": {"offset": scenario_norm.XI_OFFSET.tolist(),
                               "scale": scenario_norm.XI_SCALE.tolist()}}


def conditioning(config) -> str:
  """The run's `diffusion.conditioning` ("token" for runs made before it existed)."""
  return ego_motion.check_conditioning(config.diffusion.get("conditioning", "token"))


def class_weights(config) -> tuple[float, ...] | None:
  """The run's `diffusion.class_weights` (keep lane, lcr, lcl), checked; None where all are
  1 (the paper's balanced classes, also runs made before the field existed).

  Raises:
    ValueError: not one positive finite weight per class.
  """
  given = config.diffusion.get("class_weights")
  if given is None:
    return None
  weights = tuple(float(w) for w in given)
  if len(weights) != len(constants.CLASS_NAMES) or not all(0 < w < math.inf for w in weights):
    raise ValueError(f"diffusion.class_weights={weights}: need {len(constants.CLASS_NAMES)} "
                     f"positive finite weights, one per class {constants.CLASS_NAMES}")
  return None if all(w == 1.0 for w in weights) else weights


def unet_config(config, num_tokens: int) -> unet1d.UNetConfig:
  """The `UNetConfig` of a diffusion config (`config.model`, conditioning width)."""
  cond_dim = ego_motion.NUM_FEATURES if ego_motion.uses_film(conditioning(config)) else 0
  return to_dataclass(unet1d.UNetConfig, config.model, num_tokens=num_tokens,
                      cond_dim=cond_dim)


def diffusion_fingerprint(config: ml_collections.ConfigDict, unet: unet1d.UNetConfig,
                          dataset_id: str, tokens_meta: dict) -> dict:
  """What a denoiser checkpoint belongs to: model shape, dataset, tokeniser checkpoint
  and (beyond the paper) the ego-motion conditioning and the class weights."""
  checkpoint = tokens_meta.get("checkpoint", {})
  out = {"model": dataclasses.asdict(unet), "num_diffusion_steps": config.diffusion.num_steps,
         "control_scale": list(config.diffusion.control_scale),
         "dataset_id": dataset_id,
         "tokenizer": {"fingerprint": checkpoint.get("fingerprint"),
                       "step": checkpoint.get("step")}}
  if "params_sha256" in checkpoint:  # tokens of tokenisers trained before it lack it
    out["tokenizer"]["params_sha256"] = checkpoint["params_sha256"]
  if conditioning(config) != "token":  # token-only fingerprints stay as they were
    out["conditioning"] = {"name": conditioning(config), "features": ego_motion.NUM_FEATURES,
                           "residual_decay_s": list(config.diffusion.residual_decay_s)}
  weights = class_weights(config)
  if weights:  # balanced-class fingerprints stay as they were
    out["class_weights"] = list(weights)
  return out


def sampling_config(config) -> SamplingConfig:
  """The `SamplingConfig` of a diffusion run's config (`config.sampling`, control scale,
  conditioning)."""
  clip = config.sampling.clip_x0
  return to_dataclass(
      SamplingConfig, config.sampling, clip_x0=clip if clip > 0 else None,
      control_scale=config.diffusion.control_scale, conditioning=conditioning(config),
      residual_decay_s=config.diffusion.get("residual_decay_s",
                                            SamplingConfig.residual_decay_s))


def check_tokenizer_dir(workdir: str | os.PathLike, fingerprint: dict) -> None:
  """Checks (writing nothing) that <workdir>/tokenizer.json, if any, is intact and has
  `fingerprint` (so another Q / latent size / dataset is refused naming the differing keys).

  Raises:
    CheckpointMismatchError: the directory holds a tokeniser run of another fingerprint.
    CorruptRunError: tokenizer.json is corrupt.
  """
  path = Path(workdir) / TOKENIZER_JSON
  if path.is_file():
    saved = _read_json(path, "tokeniser")
    checkpointing.check_metadata(saved.get("fingerprint"), fingerprint, str(workdir))


def write_tokenizer_dir(workdir: str | os.PathLike, model_cfg: tokenizer_lib.TokenizerConfig,
                        fingerprint: dict) -> None:
  """Writes <workdir>/tokenizer.json (after `check_tokenizer_dir` and the checkpoint check)."""
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  if sharding.is_primary():  # one writer under jax.distributed
    checksums.write_json(workdir / TOKENIZER_JSON, {"model": dataclasses.asdict(model_cfg),
                                                    "fingerprint": fingerprint},
                         indent=1, sort_keys=True)


def write_diffusion_dir(workdir: str | os.PathLike, config: ml_collections.ConfigDict,
                        unet: unet1d.UNetConfig) -> None:
  """Writes <workdir>/config.json (the run's config) and model.json (the U-Net config)."""
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  checksums.write_json(workdir / CONFIG_JSON, json.loads(config.to_json_best_effort()))
  checksums.write_json(workdir / MODEL_JSON, {"unet": dataclasses.asdict(unet)})


def _static():
  return dataclasses.field(metadata={"static": True})


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TokenizerBundle:
  """A trained tokeniser for inference (a pytree: only `params` and `gaussians` are leaves).

  Attributes:
    params: pure dict of the model parameters.
    gaussians: the per-entry Gaussians for delta.
    graphdef: the NNX graph definition.
    config: the static model settings.
    fingerprint: the run's fingerprint (`tokenizer_fingerprint`).
    checkpoint: {"step", "params_sha256"} of the checkpoint the parameters come from
      (None for a bundle not loaded from a run).
  """

  params: dict
  gaussians: uncertainty.Gaussians
  graphdef: nnx.GraphDef = _static()
  config: tokenizer_lib.TokenizerConfig = _static()
  fingerprint: ml_collections.FrozenConfigDict = _static()
  checkpoint: ml_collections.FrozenConfigDict | None = dataclasses.field(
      default=None, metadata={"static": True})

  def tokenize(self, xi: jax.Array, mask: jax.Array):
    """Tokens of B scenarios (jittable).

    Args:
      xi: (B, 9, 75, 4) physical scenarios [x m, y m, v_x m/s, v_y m/s].
      mask: (B, 9, 75) bool.

    Returns:
      (q (B,) int32, z_hat (B, D) float32, delta (B,) float32).
    """
    z_hat, q = tokenizer_lib.encode(self.graphdef, self.params, xi, mask)
    return q, z_hat, uncertainty.mahalanobis(z_hat, q, self.gaussians)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Denoiser:
  """A trained denoiser v_theta for inference (a pytree: only `params` are leaves).

  Attributes:
    params: the EMA parameters (pure dict).
    graphdef: U-Net graph definition.
    unet: `UNetConfig`.
    config: the run's config (sampling defaults, diffusion steps, data and tokeniser dirs).
    fingerprint: what the checkpoint was trained on (`diffusion_fingerprint`).
  """

  params: dict
  graphdef: nnx.GraphDef = _static()
  unet: unet1d.UNetConfig = _static()
  config: ml_collections.FrozenConfigDict = _static()
  fingerprint: ml_collections.FrozenConfigDict = _static()

  @property
  def null_token(self) -> int:
    """The unconditional token (Q)."""
    return self.unet.null_token

  def apply(self, x: jax.Array, t: jax.Array, q: jax.Array,
            cond: jax.Array | None = None) -> jax.Array:
    """v (B, 125, 2) of normalised controls x (B, 125, 2) at steps t (B,) for tokens q (B,)
    (and, for an ego-conditioned run, ego-motion features cond (B, ego_motion.NUM_FEATURES))."""
    return unet1d.apply_unet(self.graphdef, self.params, x, t, q, cond=cond)


def _abstract(init, model_cfg) -> dict:
  """ShapeDtypeStructs of `init(model_cfg, key)`'s parameters (nothing is allocated)."""
  return jax.eval_shape(lambda key: init(model_cfg, key)[1], jax.random.key(0))


def _restore(workdir: Path, abstract: dict) -> tuple[dict, dict]:
  """(the leaves of `abstract` from the latest checkpoint, the saved fingerprint)."""
  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep),
                          abstract)
  tree, saved = checkpointing.load_latest(workdir / CHECKPOINTS, abstract, partial=True)
  return tree, saved.get("fingerprint")


def _read_json(path: Path, what: str) -> dict:
  """A checksummed JSON object; CorruptRunError naming `path` when corrupt."""
  try:
    value = checksums.read_json(path)
  except OSError as e:
    raise FileNotFoundError(f"{path}: missing or unreadable; not a {what} run directory "
                            f"({e})") from e
  if not isinstance(value, dict):
    raise CorruptRunError(f"{path}: expected a JSON object, got {type(value).__name__}")
  return value


def load_tokenizer(workdir: str | os.PathLike) -> TokenizerBundle:
  """The trained tokeniser of `workdir` for inference.

  Raises:
    FileNotFoundError: the workdir holds no tokeniser run (no tokenizer.json) or its
      outputs are missing (the run has not finished).
    CheckpointMismatchError: the checkpoint does not match the run's settings or is corrupt.
    CorruptRunError: tokenizer.json or gaussians.npz is corrupt.
    tokens.TokensMismatchError: the saved Gaussians belong to another checkpoint.
  """
  workdir = Path(workdir)
  path = workdir / TOKENIZER_JSON
  if not path.is_file():
    raise FileNotFoundError(f"{path}: missing; train the tokeniser with this workdir first")
  saved = _read_json(path, "tokeniser")
  model_cfg = to_dataclass(tokenizer_lib.TokenizerConfig, saved["model"])
  abstract = {"params": _abstract(tokenizer_lib.init_tokenizer, model_cfg),
              "step": jax.ShapeDtypeStruct((), jnp.int32)}
  state, fingerprint = _restore(workdir, abstract)
  checkpointing.check_metadata(fingerprint, saved["fingerprint"], str(workdir / CHECKPOINTS))
  gpath = tokens.gaussians_path(workdir)
  gaussians, gmeta = tokens.load_gaussians(gpath)
  checkpoint = {"step": int(state["step"]),
                "params_sha256": checkpointing.tree_digest(state["params"])}
  fitted = gmeta.get("checkpoint", {})
  for key in ("step", "params_sha256") if "params_sha256" in fitted else ("step",):
    if fitted.get(key) != checkpoint[key]:
      raise tokens.TokensMismatchError(
          f"{gpath}: Gaussians fitted on the checkpoint with {key} {fitted.get(key)}, the "
          f"checkpoint has {checkpoint[key]}; rerun train_and_evaluate")
  return TokenizerBundle(state["params"], jax.tree.map(jnp.asarray, gaussians),
                         tokenizer_lib.make_graphdef(model_cfg), model_cfg,
                         ml_collections.FrozenConfigDict(saved["fingerprint"]),
                         ml_collections.FrozenConfigDict(checkpoint))


def _restore_ema(workdir: Path, abstract: dict) -> tuple[dict, dict]:
  """(EMA params, fingerprint); also from runs that saved nnx.State leaves (`<path>/value`)."""
  try:
    tree, fingerprint = _restore(workdir, {"ema_params": abstract})
    return tree["ema_params"], fingerprint
  except CheckpointMismatchError as error:
    wrapped = jax.tree.map(lambda x: {"value": x}, abstract)
    try:
      tree, fingerprint = _restore(workdir, {"ema_params": wrapped})
    except CheckpointMismatchError:
      raise error from None
  is_wrapped = lambda d: isinstance(d, dict) and set(d) == {"value"}
  return jax.tree.map(lambda d: d["value"], tree["ema_params"], is_leaf=is_wrapped), fingerprint


def load_denoiser(workdir: str | os.PathLike) -> Denoiser:
  """The EMA denoiser of the latest checkpoint of a diffusion run, for inference.

  Raises:
    FileNotFoundError: no config.json / model.json (not a diffusion run directory).
    CorruptRunError: config.json or model.json is corrupt.
    CheckpointMismatchError: no complete checkpoint, one of another model size, or a
      corrupt one; or a denoiser trained on another number of ego-motion features.
  """
  workdir = Path(workdir)
  config = _read_json(workdir / CONFIG_JSON, "diffusion")
  unet = to_dataclass(unet1d.UNetConfig, _read_json(workdir / MODEL_JSON, "diffusion")["unet"])
  if unet.cond_dim not in (0, ego_motion.NUM_FEATURES):
    raise CheckpointMismatchError(
        f"{workdir}: the denoiser was trained on {unet.cond_dim} ego-motion features, this "
        f"version of cvmdx_jax computes {ego_motion.NUM_FEATURES} (cvmdx_jax/ego_motion.py, "
        "FEATURES); retrain it")
  params, fingerprint = _restore_ema(workdir, _abstract(unet1d.init_unet, unet))
  return Denoiser(params, unet1d.make_graphdef(unet), unet,
                  ml_collections.FrozenConfigDict(config),
                  ml_collections.FrozenConfigDict(fingerprint or {}))
