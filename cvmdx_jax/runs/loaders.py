"""Reading trained run directories into plain parts: parameters restored into an abstract
tree built from the saved model config (only what inference needs: the tokeniser's
parameters and step, the denoiser's EMA parameters, a baseline's val-chosen parameters),
the typed run config, the fingerprint. No optimiser and no trainer code is involved (this
module imports nothing from `cvmdx_jax.train`); `inference.bundles` wraps the parts into
the bundles that predict. Files are verified on reading (`storage.checksums`,
`storage.checkpointing`); a run directory of an older version of cvmdx_jax is refused
(retrain it, or re-import the official checkpoint).
"""

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections

from cvmdx_jax import sharding
from cvmdx_jax.config.fields import to_dataclass
from cvmdx_jax.config.models import TokenizerConfig
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import fingerprints, layout, tokens
from cvmdx_jax.storage import checkpointing, identity
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError
from cvmdx_jax.storage.checksums import CorruptRunError
from cvmdx_jax.storage.identity import content_id


def restore_latest(workdir: Path, abstract: dict) -> tuple[dict, dict]:
  """(the leaves of `abstract` from the latest checkpoint, the saved fingerprint)."""
  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep), abstract)
  tree, saved = checkpointing.load_latest(workdir / layout.CHECKPOINTS, abstract, partial=True)
  return tree, saved["fingerprint"]


def read_run_config(workdir: Path, cls, what: str):
  """The typed config (`cls.from_config`) of <workdir>/config.json; a config.json that is
  not one of this version is a CheckpointMismatchError naming the file."""
  path = workdir / layout.CONFIG_JSON
  try:
    return cls.from_config(layout.read_json(path, what))
  except CorruptRunError:
    raise
  except ValueError as e:
    raise CheckpointMismatchError(
        f"{path}: {e}; a run of another version of cvmdx_jax: " "retrain it"
    ) from e
  except (KeyError, TypeError, AttributeError) as e:  # a section missing or of another kind
    raise CheckpointMismatchError(
        f"{path}: not the config of a {what} run (its section {e} is missing or not a "
        f"section): another kind of run (a baseline run where a {what} run is expected?) "
        "or another version"
    ) from e


def read_tokenizer(workdir: str | os.PathLike):
  """(params, gaussians, model config, fingerprint, checkpoint) of the tokeniser run in
  `workdir`: its latest checkpoint's parameters, the per-entry Gaussians of delta, its
  `TokenizerConfig`, its fingerprint and {"fingerprint", "step", "params_id"} of the
  checkpoint (`fingerprints.tokenizer_checkpoint`).

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
  abstract = {
      "params": tokenizer_lib.abstract_params(model_cfg),
      "step": jax.ShapeDtypeStruct((), jnp.int32),
  }
  state, fingerprint = restore_latest(workdir, abstract)
  identity.check(
      fingerprint,
      saved["fingerprint"],
      f"checkpoint {workdir / layout.CHECKPOINTS}",
      CheckpointMismatchError,
  )
  gpath = tokens.gaussians_path(workdir)
  gaussians, gmeta = tokens.load_gaussians(gpath)
  checkpoint = {
      "fingerprint": saved["fingerprint"],
      "step": int(state["step"]),
      "params_id": content_id(state["params"]),
  }
  identity.check(
      fingerprints.tokenizer_checkpoint(gmeta),
      checkpoint,
      f"{gpath} (Gaussians fitted on another checkpoint; retrain the tokeniser)",
      tokens.TokensMismatchError,
  )
  return (
      state["params"],
      gaussians,
      model_cfg,
      ml_collections.FrozenConfigDict(saved["fingerprint"]),
      ml_collections.FrozenConfigDict(checkpoint),
  )


def read_denoiser(workdir: str | os.PathLike):
  """(config, EMA params, fingerprint) of the latest checkpoint of a diffusion run.

  Raises:
    FileNotFoundError: no config.json (not a diffusion run directory).
    CorruptRunError: config.json is corrupt.
    CheckpointMismatchError: config.json is not a `DiffusionRunConfig` of this version (e.g.
      another number of ego-motion features); no complete checkpoint, one of another
      model size, or a corrupt one.
  """
  workdir = Path(workdir)
  config = read_run_config(workdir, DiffusionRunConfig, "diffusion")
  tree, fingerprint = restore_latest(workdir, {"ema_params": unet1d.abstract_params(config.model)})
  return config, tree["ema_params"], ml_collections.FrozenConfigDict(fingerprint)


def load_val_chosen(workdir: str | os.PathLike, run_cls, abstract_params, what: str):
  """(config, params, fingerprint, epoch) of a run whose train state keeps the val-chosen
  parameters in "best" (`train.baseline.make_init_fn`): its `run_cls` config.json, the
  parameters of `abstract_params(config.model)`'s structure, the saved fingerprint and the
  chosen epoch; raises as `load_baseline` does, naming a `what` run directory."""
  workdir = Path(workdir)
  config = read_run_config(workdir, run_cls, what)
  abstract = {
      "best": {
          "params": abstract_params(config.model),
          "epoch": jax.ShapeDtypeStruct((), jnp.int32),
      }
  }
  tree, fingerprint = restore_latest(workdir, abstract)
  return (
      config,
      tree["best"]["params"],
      ml_collections.FrozenConfigDict(fingerprint),
      int(tree["best"]["epoch"]),
  )
