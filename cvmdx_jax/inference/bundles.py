"""The trained-model bundles that predict: a `TokenizerBundle` (scenarios -> tokens, latent,
delta), a `Denoiser` (the EMA U-Net with its run config) and a `LearnedBaseline` (the
multiple-choice MLP), each a pytree whose parameters are its leaves, and their loaders
`load_tokenizer`, `load_denoiser`, `load_baseline` (the files are read by `runs.loaders`).
"""

import dataclasses
import os

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from cvmdx_jax import ego_motion
from cvmdx_jax.config.models import TokenizerConfig, UNetConfig
from cvmdx_jax.config.runs import BaselineRunConfig, DiffusionRunConfig
from cvmdx_jax.models import multiple_choice as mc
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models import uncertainty, unet1d
from cvmdx_jax.runs import loaders


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
      default=None, metadata={"static": True}
  )

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

  def apply(
      self, x: jax.Array, t: jax.Array, q: jax.Array, cond: jax.Array | None = None
  ) -> jax.Array:
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
    out = _hypotheses(self, *baseline_inputs(q, delta, xi, mask, v0, psi0))
    return tuple(np.asarray(a) for a in out)


def baseline_inputs(q, delta, xi, mask, v0, psi0) -> tuple[jax.Array, ...]:
  """A learned baseline's inputs as the arrays its jitted call takes: q int32, delta, xi, v0,
  psi0 float32, mask bool (shapes as `LearnedBaseline.__call__`)."""
  return (
      jnp.asarray(q, jnp.int32),
      jnp.asarray(delta, jnp.float32),
      jnp.asarray(xi, jnp.float32),
      jnp.asarray(mask, bool),
      jnp.asarray(v0, jnp.float32),
      jnp.asarray(psi0, jnp.float32),
  )


@jax.jit
def _hypotheses(baseline: LearnedBaseline, q, delta, xi, mask, v0, psi0):
  ego = ego_motion.ego_features(xi, mask)
  return mc.hypotheses(
      baseline.graphdef, baseline.params, baseline.config.model, q, delta, ego, v0, psi0
  )


def load_tokenizer(workdir: str | os.PathLike) -> TokenizerBundle:
  """The trained tokeniser of `workdir` for inference (raises as `runs.loaders.read_tokenizer`)."""
  params, gaussians, model_cfg, fingerprint, checkpoint = loaders.read_tokenizer(workdir)
  return TokenizerBundle(
      params,
      jax.tree.map(jnp.asarray, gaussians),
      tokenizer_lib.make_graphdef(model_cfg),
      model_cfg,
      fingerprint,
      checkpoint,
  )


def load_denoiser(workdir: str | os.PathLike) -> Denoiser:
  """The EMA denoiser of the latest checkpoint of a diffusion run, for inference (raises as
  `runs.loaders.read_denoiser`)."""
  config, params, fingerprint = loaders.read_denoiser(workdir)
  return Denoiser(params, unet1d.make_graphdef(config.model), config, fingerprint)


def load_baseline(workdir: str | os.PathLike) -> LearnedBaseline:
  """The val-chosen parameters of a baseline run (`cvmdx_jax.train.baseline`), for inference.

  Raises:
    FileNotFoundError: no config.json (not a baseline run directory).
    CorruptRunError: config.json is corrupt.
    CheckpointMismatchError: config.json is not a `BaselineRunConfig` of this version; no
      complete checkpoint, one of another model size (e.g. another number of ego-motion
      features), or a corrupt one.
  """
  config, params, fingerprint, epoch = loaders.load_val_chosen(
      workdir, BaselineRunConfig, mc.abstract_params, "baseline"
  )
  return LearnedBaseline(params, mc.make_graphdef(config.model), config, fingerprint, epoch)
