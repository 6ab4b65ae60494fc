"""The files of a run directory and their writers (docs/design.md, "Run directories").

A tokeniser run (`cvmdx_jax.train.tokenizer`):

    <dir>/tokenizer.json         {"model": TokenizerConfig fields, "fingerprint": ...}
    <dir>/checkpoints/<epoch>/   train state {"step", "params", "opt_state", "usage"}
    <dir>/metrics.jsonl          one JSON line per epoch
    <dir>/tokens/                tokens per split and the per-entry Gaussians (`runs.tokens`)

A diffusion run (`cvmdx_jax.train.diffusion`):

    <dir>/config.json            its `config.runs.DiffusionRunConfig` (model.num_tokens = Q)
    <dir>/checkpoints/<epoch>/   train state {"step", "params", "ema_params", "opt_state"}
    <dir>/metrics.jsonl

A baseline run (`cvmdx_jax.train.baseline`):

    <dir>/config.json            its `config.runs.BaselineRunConfig` (model.num_tokens = Q)
    <dir>/checkpoints/<epoch>/   train state {"params", "opt_state", "step", "val", "best"}
    <dir>/metrics.jsonl          train loss and the val curve per epoch

tokenizer.json, config.json and tokens/*.npz are checksummed (`storage.checksums`, one
checksums.json per directory), and so is every file of a checkpoint step
(`storage.checkpointing`). The trainers write these files only after the resumed
checkpoint's fingerprint has been checked (`train.loop.train`'s `on_start`).
"""

import dataclasses
import os
from pathlib import Path

from cvmdx_jax import sharding
from cvmdx_jax.config.models import TokenizerConfig
from cvmdx_jax.storage import checksums
from cvmdx_jax.storage.checksums import CorruptRunError

CHECKPOINTS = "checkpoints"  # orbax step directories (`storage.checkpointing`)
METRICS = "metrics.jsonl"
TOKENIZER_JSON = "tokenizer.json"
CONFIG_JSON = "config.json"


def read_json(path: Path, what: str) -> dict:
  """A checksummed JSON object of a run; FileNotFoundError / CorruptRunError naming `path`."""
  try:
    value = checksums.read_json(path)
  except OSError as e:
    raise FileNotFoundError(
        f"{path}: missing or unreadable; not a {what} run directory " f"({e})"
    ) from e
  if not isinstance(value, dict):
    raise CorruptRunError(f"{path}: expected a JSON object, got {type(value).__name__}")
  return value


def saved_tokenizer_fingerprint(workdir: str | os.PathLike) -> dict | None:
  """The fingerprint in <workdir>/tokenizer.json (verified), None where there is none."""
  path = Path(workdir) / TOKENIZER_JSON
  return read_json(path, "tokeniser").get("fingerprint") if path.is_file() else None


def write_tokenizer_dir(
    workdir: str | os.PathLike, model_cfg: TokenizerConfig, fingerprint: dict
) -> None:
  """Writes <workdir>/tokenizer.json (process 0 of a distributed run)."""
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  if sharding.is_primary():
    checksums.write_json(
        workdir / TOKENIZER_JSON,
        {"model": dataclasses.asdict(model_cfg), "fingerprint": fingerprint},
        indent=1,
        sort_keys=True,
    )


def write_run_config(workdir: str | os.PathLike, config) -> None:
  """Writes <workdir>/config.json, the run's `DiffusionRunConfig` or `BaselineRunConfig`
  (process 0)."""
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  if sharding.is_primary():
    checksums.write_json(workdir / CONFIG_JSON, dataclasses.asdict(config))
