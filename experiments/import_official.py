"""Imports an official cVMDx checkpoint (PyTorch state dict, no torch needed) as a
diffusion run directory that `load_denoiser` and `Predictor.load` accept.

  .venv/bin/python experiments/import_official.py --checkpoint=ema_0.9999_080000.pt \\
      --workdir=runs/official_diffusion [--tokenizer_dir=runs/tokenizer]

Q is read from the label embedding (Q + 1 rows, the last the null label). The run's
config is `configs/diffusion.py:reference` with the checkpoint's U-Net sizes, control
scale (4 m/s^2, 0.7 rad/s) and `sampling.mode="official"` (override at inference
with `Predictor.load(..., sampling=...)`). `--tokenizer_dir` pairs the run with a
tokeniser of ours (its codebook size must be Q), so that `Predictor.load` accepts the
pair; without it the run loads with `load_denoiser` only. `--workdir` must not exist;
it appears complete or not at all.
"""

import dataclasses
import hashlib
import shutil
import tempfile
from pathlib import Path

from absl import flags
import jax
import jax.numpy as jnp

from configs import diffusion as diffusion_configs
from cvmdx_jax import cli, targets
from cvmdx_jax.models import official_import
from cvmdx_jax.runs import fingerprints, layout, loaders
from cvmdx_jax.runs.config import DiffusionConfig
from cvmdx_jax.storage import checkpointing

_CHECKPOINT = flags.DEFINE_string("checkpoint", None, "Official model or EMA state dict (.pt).")
_WORKDIR = flags.DEFINE_string("workdir", None, "New diffusion run directory to write.")
_KEY = flags.DEFINE_string("key", None, "Entry of a dict holding several state dicts.")
_NUM_HEADS = flags.DEFINE_integer("num_heads", official_import.OFFICIAL_NUM_HEADS,
                                  "Attention heads of the official model (not stored in it).",
                                  lower_bound=1)
_TOKENIZER_DIR = flags.DEFINE_string("tokenizer_dir", None,
                                     "Tokeniser run to pair with (codebook size Q).")
flags.mark_flags_as_required(["checkpoint", "workdir"])
cli.input_dirs("tokenizer_dir")
cli.output_dirs("workdir")


def write_run(workdir: Path, config: DiffusionConfig, params, fingerprint: dict) -> None:
  """Writes a diffusion run directory in the `cvmdx_jax.runs.layout` format: config.json
  and checkpoints/1 holding {params, ema_params} (both the imported weights) and step 0,
  with metadata {"fingerprint": fingerprint}."""
  layout.write_diffusion_dir(workdir, config)
  state = {"params": params, "ema_params": jax.tree.map(jnp.copy, params),
           "step": jnp.zeros((), jnp.int32)}
  with checkpointing.Checkpoints(workdir / layout.CHECKPOINTS, keep=1) as ckpts:
    ckpts.save(1, state, {"fingerprint": fingerprint})


def main(argv):
  del argv
  checkpoint, workdir = Path(_CHECKPOINT.value), Path(_WORKDIR.value)
  if workdir.exists():
    raise ValueError(f"--workdir={workdir} exists; give a new directory")
  if not checkpoint.is_file():
    raise FileNotFoundError(f"--checkpoint={checkpoint}: no such file")
  cfg, params = official_import.load_official(checkpoint, key=_KEY.value,
                                              num_heads=_NUM_HEADS.value)
  tokens_meta = {}
  config = diffusion_configs.get_config("reference")
  config.tokenizer_dir = ""  # none paired
  if _TOKENIZER_DIR.value:
    bundle = loaders.load_tokenizer(_TOKENIZER_DIR.value)
    if bundle.config.quantizer.codebook_size != cfg.num_tokens:
      raise ValueError(f"--tokenizer_dir={_TOKENIZER_DIR.value} has codebook size "
                       f"{bundle.config.quantizer.codebook_size}, the checkpoint Q = "
                       f"{cfg.num_tokens}")
    tokens_meta = {"checkpoint": bundle.checkpoint.to_dict()}  # fingerprint, step, params_id
    config.tokenizer_dir = _TOKENIZER_DIR.value
  config.diffusion.control_scale = targets.PAPER_SCALE  # the official (4, 0.7)
  config.sampling.mode = "official"
  config = dataclasses.replace(DiffusionConfig.from_config(config), model=cfg)
  digest = hashlib.sha256(checkpoint.read_bytes()).hexdigest()[:16]
  fingerprint = fingerprints.diffusion(config, f"official:{digest}", tokens_meta)
  workdir.parent.mkdir(parents=True, exist_ok=True)
  tmp = Path(tempfile.mkdtemp(prefix=f".{workdir.name}.", dir=workdir.parent))
  try:
    write_run(tmp / "run", config, params, fingerprint)
    (tmp / "run").rename(workdir)
  finally:
    shutil.rmtree(tmp)
  print(f"imported {checkpoint} (Q = {cfg.num_tokens}, "
        f"{sum(x.size for x in jax.tree.leaves(params)):,} parameters) into {workdir}")


if __name__ == "__main__":
  cli.run(main)
