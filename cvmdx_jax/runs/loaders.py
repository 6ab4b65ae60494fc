"""The inference loaders of run directories: a `TokenizerBundle`, a `Denoiser` and a
`LearnedBaseline`.

`load_tokenizer`, `load_denoiser` and `load_baseline` restore only what inference needs
(the tokeniser's parameters and step, the denoiser's EMA parameters, the baseline's
val-chosen parameters) into an abstract tree built from the
saved model config: no optimiser and no trainer code is involved (this module imports
nothing from `cvmdx_jax.train`). Files are verified on reading (`storage.checksums`,
`storage.checkpointing`); a run directory of an older version of cvmdx_jax is refused
(retrain it, or re-import the official checkpoint).
"""

import dataclasses
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from cvmdx_jax import ego_motion, sharding
from cvmdx_jax.config.fields import to_dataclass
from cvmdx_jax.config.models import TokenizerConfig, UNetConfig
from cvmdx_jax.config.runs import BaselineRunConfig, DiffusionRunConfig
from cvmdx_jax.models import multiple_choice as mc
from cvmdx_jax.models import unet1d, uncertainty
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.runs import fingerprints, layout, tokens
from cvmdx_jax.storage import checkpointing, identity
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.storage.checksums import CorruptRunError
from cvmdx_jax.storage.identity import content_id


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
    fingerprint: the run's fingerprint (`fingerprints.tokenizer`).
    checkpoint: {"fingerprint", "step", "params_id"} of the checkpoint the parameters come
      from (`fingerprints.tokenizer_checkpoint`; None for a bundle not loaded from a run).
  """

  params: dict
  gaussians: uncertainty.Gaussians
  graphdef: nnx.GraphDef = _static()
  config: TokenizerConfig = _static()
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
    config: the run's `DiffusionRunConfig` (U-Net in `config.model`, its targets in
      `config.diffusion`, default sampling in `config.sampling`).
    fingerprint: what the checkpoint was trained on (`fingerprints.diffusion`).
  """

  params: dict
  graphdef: nnx.GraphDef = _static()
  config: DiffusionRunConfig = _static()
  fingerprint: ml_collections.FrozenConfigDict = _static()

  @property
  def unet(self) -> UNetConfig:
    return self.config.model

  @property
  def progressive(self) -> bool:
    """Whether this is a progressive student (`train.distill`), which samples only its own
    steps."""
    stage = self.fingerprint.to_dict().get("distill", {}).get("stage")
    return stage in ("progressive", "guided_progressive")

  @property
  def null_token(self) -> int:
    """The unconditional token (Q)."""
    return self.config.model.null_token

  def apply(self, x: jax.Array, t: jax.Array, q: jax.Array,
            cond: jax.Array | None = None) -> jax.Array:
    """v (B, 125, 2) of normalised controls x (B, 125, 2) at steps t (B,) for tokens q (B,)
    (and, for an ego-conditioned run, ego-motion features cond (B, ego_motion.NUM_FEATURES))."""
    return unet1d.apply_unet(self.graphdef, self.params, x, t, q, cond=cond)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class LearnedBaseline:
  """A trained multiple-choice MLP for inference (a pytree: only `params` are leaves).

  Attributes:
    params: the parameters of the epoch chosen on val.
    graphdef: the NNX graph definition.
    config: the run's `BaselineRunConfig` (the MLP in `config.model`).
    fingerprint: what it was trained on (`fingerprints.baseline`).
    epoch: the chosen epoch.
  """

  params: dict
  graphdef: nnx.GraphDef = _static()
  config: BaselineRunConfig = _static()
  fingerprint: ml_collections.FrozenConfigDict = _static()
  epoch: int = dataclasses.field(default=0, metadata={"static": True})

  def __call__(self, q, delta, xi, mask, v0, psi0):
    """(trajectories (M, K, 125, 2) m, probabilities (M, K)) from tokens q (M,), delta
    (M,) and the observed scenarios xi (M, 9, 75, 4), mask (M, 9, 75), v0, psi0 (M,)."""
    out = _hypotheses(self, jnp.asarray(q, jnp.int32), jnp.asarray(delta, jnp.float32),
                      jnp.asarray(xi, jnp.float32), jnp.asarray(mask, bool),
                      jnp.asarray(v0, jnp.float32), jnp.asarray(psi0, jnp.float32))
    return tuple(np.asarray(a) for a in out)


@jax.jit
def _hypotheses(baseline: LearnedBaseline, q, delta, xi, mask, v0, psi0):
  ego = ego_motion.ego_features(xi, mask)
  return mc.hypotheses(baseline.graphdef, baseline.params, baseline.config.model, q, delta,
                       ego, v0, psi0)


def _abstract(init, model_cfg) -> dict:
  """ShapeDtypeStructs of `init(model_cfg, key)`'s parameters (nothing is allocated)."""
  return jax.eval_shape(lambda key: init(model_cfg, key)[1], jax.random.key(0))


def _restore(workdir: Path, abstract: dict) -> tuple[dict, dict]:
  """(the leaves of `abstract` from the latest checkpoint, the saved fingerprint)."""
  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep),
                          abstract)
  tree, saved = checkpointing.load_latest(workdir / layout.CHECKPOINTS, abstract, partial=True)
  return tree, saved["fingerprint"]


def _run_config(workdir: Path, cls, what: str):
  """The typed config (`cls.from_config`) of <workdir>/config.json; a config.json that is
  not one of this version is a CheckpointMismatchError naming the file."""
  path = workdir / layout.CONFIG_JSON
  try:
    return cls.from_config(layout.read_json(path, what))
  except CorruptRunError:
    raise
  except ValueError as e:
    raise CheckpointMismatchError(f"{path}: {e}; a run of another version of cvmdx_jax: "
                                  "retrain it") from e


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
  path = workdir / layout.TOKENIZER_JSON
  if not path.is_file():
    raise FileNotFoundError(f"{path}: missing; train the tokeniser with this workdir first")
  saved = layout.read_json(path, "tokeniser")
  model_cfg = to_dataclass(TokenizerConfig, saved["model"])
  abstract = {"params": _abstract(tokenizer_lib.init_tokenizer, model_cfg),
              "step": jax.ShapeDtypeStruct((), jnp.int32)}
  state, fingerprint = _restore(workdir, abstract)
  identity.check(fingerprint, saved["fingerprint"], f"checkpoint {workdir / layout.CHECKPOINTS}",
                     CheckpointMismatchError)
  gpath = tokens.gaussians_path(workdir)
  gaussians, gmeta = tokens.load_gaussians(gpath)
  checkpoint = {"fingerprint": saved["fingerprint"], "step": int(state["step"]),
                "params_id": content_id(state["params"])}
  identity.check(fingerprints.tokenizer_checkpoint(gmeta), checkpoint,
                     f"{gpath} (Gaussians fitted on another checkpoint; retrain the tokeniser)",
                     tokens.TokensMismatchError)
  return TokenizerBundle(state["params"], jax.tree.map(jnp.asarray, gaussians),
                         tokenizer_lib.make_graphdef(model_cfg), model_cfg,
                         ml_collections.FrozenConfigDict(saved["fingerprint"]),
                         ml_collections.FrozenConfigDict(checkpoint))


def load_denoiser(workdir: str | os.PathLike) -> Denoiser:
  """The EMA denoiser of the latest checkpoint of a diffusion run, for inference.

  Raises:
    FileNotFoundError: no config.json (not a diffusion run directory).
    CorruptRunError: config.json is corrupt.
    CheckpointMismatchError: config.json is not a `DiffusionRunConfig` of this version (e.g.
      another number of ego-motion features); no complete checkpoint, one of another
      model size, or a corrupt one.
  """
  workdir = Path(workdir)
  config = _run_config(workdir, DiffusionRunConfig, "diffusion")
  tree, fingerprint = _restore(workdir, {"ema_params": _abstract(unet1d.init_unet,
                                                                 config.model)})
  return Denoiser(tree["ema_params"], unet1d.make_graphdef(config.model), config,
                  ml_collections.FrozenConfigDict(fingerprint))


def load_baseline(workdir: str | os.PathLike) -> LearnedBaseline:
  """The val-chosen parameters of a baseline run (`cvmdx_jax.train.baseline`), for inference.

  Raises:
    FileNotFoundError: no config.json (not a baseline run directory).
    CorruptRunError: config.json is corrupt.
    CheckpointMismatchError: config.json is not a `BaselineRunConfig` of this version; no
      complete checkpoint, one of another model size (e.g. another number of ego-motion
      features), or a corrupt one.
  """
  config, params, fingerprint, epoch = load_val_chosen(workdir, BaselineRunConfig, mc.init,
                                                       "baseline")
  return LearnedBaseline(params, mc.make_graphdef(config.model), config, fingerprint, epoch)


def load_val_chosen(workdir: str | os.PathLike, run_cls, init, what: str):
  """(config, params, fingerprint, epoch) of a run whose train state keeps the val-chosen
  parameters in "best" (`train.baseline.make_init_fn`): its `run_cls` config.json, the
  parameters of `init(config.model, key)`'s structure, the saved fingerprint and the
  chosen epoch; raises as `load_baseline` does, naming a `what` run directory."""
  workdir = Path(workdir)
  config = _run_config(workdir, run_cls, what)
  abstract = {"best": {"params": _abstract(init, config.model),
                       "epoch": jax.ShapeDtypeStruct((), jnp.int32)}}
  tree, fingerprint = _restore(workdir, abstract)
  return (config, tree["best"]["params"], ml_collections.FrozenConfigDict(fingerprint),
          int(tree["best"]["epoch"]))
