"""experiments/import_official.py on a full disk: the run is written whole or not at all
(issue 48's probe found `.import.*` directories left behind)."""

import errno
import os

import jax
import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.models import unet1d
from cvmdx_jax.storage import locking
from experiments import import_official


def _entries(workdir) -> list[str]:
  """The names in `workdir` but its lock files ([] when it is gone)."""
  if not workdir.exists():
    return []
  return sorted(p.name for p in workdir.iterdir() if not p.name.startswith(locking.LOCK_NAME))


def test_a_failed_import_leaves_an_empty_workdir_and_the_retry_writes_the_run(
    tmp_path, monkeypatch
):
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("tiny")).with_tokens(4)
  params = unet1d.init_unet(config.model, jax.random.key(0))[1]
  workdir = tmp_path / "run"
  write = import_official.layout.write_run_config

  def full(*args):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(workdir / "config.json"))

  monkeypatch.setattr(import_official.layout, "write_run_config", full)  # after the checkpoint
  with pytest.raises(OSError, match="No space left"):
    import_official._write_once(workdir, config, params, {})
  assert _entries(workdir) == []
  monkeypatch.setattr(import_official.layout, "write_run_config", write)
  import_official._write_once(workdir, config, params, {})  # the rerun is not refused
  assert _entries(workdir) == ["checkpoints", "checksums.json", "config.json"]
