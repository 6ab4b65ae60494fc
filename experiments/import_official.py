"""Imports an official cVMDx checkpoint (PyTorch state dict, no torch needed) as a
diffusion run directory that `load_denoiser` and `Predictor.load` accept.

  .venv/bin/python experiments/import_official.py --checkpoint=ema_0.9999_080000.pt \\
      --workdir=runs/official_diffusion [--tokenizer_dir=runs/tokenizer]

Q is read from the label embedding (Q + 1 rows, the last the null label). The run's
config is `configs/diffusion.py:reference` with the checkpoint's U-Net sizes, control
scale (4 m/s^2, 0.7 rad/s) and `sampling.mode="official"` (override at inference
with `Predictor.load(..., sampling=...)`). `--tokenizer_dir` pairs the run with a
tokeniser of ours (its codebook size must be Q), so that `Predictor.load` accepts the
pair; without it the run loads with `load_denoiser` only. The checkpoint is checked
whole (shapes against the architecture it implies, finite weights, `--num_heads`
dividing the attention channels) before anything is written. `--workdir` must be new
or empty; it is held (`locking.hold`) while written, so a second import into it is
refused, and it gets config.json last: a run with config.json is complete.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
from absl import flags

from configs import diffusion as diffusion_configs
from cvmdx_jax.config.denoiser import PAPER_SCALE
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference.bundles import load_tokenizer
from cvmdx_jax.models import official_import
from cvmdx_jax.models.official_state import OFFICIAL_NUM_HEADS, NumHeadsError
from cvmdx_jax.runs import fingerprints, layout
from cvmdx_jax.storage import checkpointing, checksums, locking

_CHECKPOINT = flags.DEFINE_string("checkpoint", None, "Official model or EMA state dict (.pt).")
_WORKDIR = flags.DEFINE_string("workdir", None, "New diffusion run directory to write.")
_KEY = flags.DEFINE_string("key", None, "Entry of a dict holding several state dicts.")
_NUM_HEADS = flags.DEFINE_integer(
    "num_heads",
    OFFICIAL_NUM_HEADS,
    "Attention heads of the official model (not stored in it).",
    lower_bound=1,
)
_TOKENIZER_DIR = flags.DEFINE_string(
    "tokenizer_dir", None, "Tokeniser run to pair with (codebook size Q)."
)
flags.mark_flags_as_required(["checkpoint", "workdir"])
cli.input_dirs("tokenizer_dir")
cli.output_dirs("workdir")


def write_run(workdir: Path, config: DiffusionRunConfig, params, fingerprint: dict) -> None:
  """Writes a diffusion run directory in the `cvmdx_jax.runs.layout` format: checkpoints/1
  holding {params, ema_params} (both the imported weights) and step 0, with metadata
  {"fingerprint": fingerprint}, then config.json (`storage.checksums`): a directory is a run
  once its config.json is there (`inference.bundles.load_denoiser` refuses it before)."""
  state = {
      "params": params,
      "ema_params": jax.tree.map(jnp.copy, params),
      "step": jnp.zeros((), jnp.int32),
  }
  with checkpointing.Checkpoints(workdir / layout.CHECKPOINTS, keep=1) as ckpts:
    ckpts.save(1, state, {"fingerprint": fingerprint})
  layout.write_run_config(workdir, config)


def _write_once(workdir: Path, config: DiffusionRunConfig, params, fingerprint: dict) -> None:
  """`write_run` into a new or empty `workdir`, held; on failure the checkpoints are removed
  again. Checkpoints without a config.json are an import that was killed (the lock says
  none is running): removed first."""
  checkpoints = workdir / layout.CHECKPOINTS
  with locking.hold(workdir):
    if checkpoints.is_dir() and not (workdir / layout.CONFIG_JSON).exists():
      shutil.rmtree(checkpoints)
    found = sorted(p.name for p in workdir.iterdir() if not p.name.startswith(locking.LOCK_NAME))
    if found:
      raise UserError(f"--workdir={workdir} exists and holds {found[:4]}; give a new directory")
    try:
      write_run(workdir, config, params, fingerprint)
    except BaseException:
      if not (workdir / layout.CONFIG_JSON).exists():
        shutil.rmtree(checkpoints, ignore_errors=True)
      raise


def main(argv):
  del argv
  checkpoint, workdir = Path(_CHECKPOINT.value), Path(_WORKDIR.value)
  if not checkpoint.is_file():
    raise FileNotFoundError(f"--checkpoint={checkpoint}: no such file")
  try:
    cfg, params = official_import.load_official(
        checkpoint, key=_KEY.value, num_heads=_NUM_HEADS.value
    )
  except NumHeadsError as e:
    raise UserError(f"--num_heads={_NUM_HEADS.value}: {e}") from None
  tokens_meta = {}
  config = diffusion_configs.get_config("reference")
  config.tokenizer_dir = ""  # none paired
  if _TOKENIZER_DIR.value:
    bundle = load_tokenizer(_TOKENIZER_DIR.value)
    if bundle.config.quantizer.codebook_size != cfg.num_tokens:
      raise UserError(
          f"--tokenizer_dir={_TOKENIZER_DIR.value} has codebook size "
          f"{bundle.config.quantizer.codebook_size}, the checkpoint Q = "
          f"{cfg.num_tokens}"
      )
    tokens_meta = {"checkpoint": bundle.checkpoint.to_dict()}  # fingerprint, step, params_id
    config.tokenizer_dir = _TOKENIZER_DIR.value
  config.diffusion.control_scale = PAPER_SCALE  # the official (4, 0.7)
  config.sampling.mode = "official"
  config = dataclasses.replace(DiffusionRunConfig.from_config(config), model=cfg)
  digest = checksums.file_sha256(checkpoint)[:16]
  fingerprint = fingerprints.diffusion(config, f"official:{digest}", tokens_meta)
  _write_once(workdir, config, params, fingerprint)
  print(
      f"imported {checkpoint} (Q = {cfg.num_tokens}, "
      f"{sum(x.size for x in jax.tree.leaves(params)):,} parameters) into {workdir}"
  )


if __name__ == "__main__":
  cli.run(main)
