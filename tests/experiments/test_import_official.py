"""experiments/import_official.py on a full disk: the run is written whole or not at all
(issue 48's probe found `.import.*` directories left behind). In a subprocess: importing
the script defines its required absl flags, which would fail other in-process flag tests."""

import subprocess
import sys

from tests.subprocess_env import REPO, environ

_FAILED_THEN_RETRIED = """
import errno, os, sys
from pathlib import Path
import jax
from configs import diffusion as diffusion_config
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.models import unet1d
from cvmdx_jax.storage import locking
from experiments import import_official

workdir = Path(sys.argv[1])
config = DiffusionRunConfig.from_config(diffusion_config.get_config("tiny")).with_tokens(4)
params = unet1d.init_unet(config.model, jax.random.key(0))[1]

def entries():  # the names in workdir but its lock files ([] when it is gone)
  if not workdir.exists():
    return []
  return sorted(p.name for p in workdir.iterdir() if not p.name.startswith(locking.LOCK_NAME))

write = import_official.layout.write_run_config
def full(*args):  # the disk fills after the checkpoint, at config.json
  raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(workdir / "config.json"))
import_official.layout.write_run_config = full
try:
  import_official._write_once(workdir, config, params, {})
except OSError as e:
  print("failed:", e.strerror, entries())
import_official.layout.write_run_config = write
import_official._write_once(workdir, config, params, {})  # the rerun is not refused
print("retried:", entries())
"""


def test_a_failed_import_leaves_an_empty_workdir_and_the_retry_writes_the_run(tmp_path):
  done = subprocess.run(
      [sys.executable, "-c", _FAILED_THEN_RETRIED, str(tmp_path / "run")],
      cwd=REPO,
      env=environ(JAX_PLATFORMS="cpu"),
      capture_output=True,
      text=True,
      timeout=300,
  )
  assert done.returncode == 0, done.stderr[-3000:]
  assert done.stdout.splitlines() == [
      "failed: No space left on device []",
      "retried: ['checkpoints', 'checksums.json', 'config.json']",
  ]
