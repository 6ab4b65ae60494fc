"""The PYTHONPATH and environment of the entry points and scripts the tests start in
subprocesses."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def pythonpath() -> str:
  """This checkout first, then the caller's PYTHONPATH: dependencies installed there (a
  GPU image's `pip install --target`, an HPC module) stay importable in the subprocess."""
  return os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)


def environ(**extra: str) -> dict[str, str]:
  """The caller's environment with `pythonpath()` and `extra` (e.g. JAX_PLATFORMS="cpu")."""
  return dict(os.environ, PYTHONPATH=pythonpath(), **extra)


def run_script(script: str, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
  """`experiments/<script>.py args` on the CPU from the repository root, output captured."""
  return subprocess.run(
      [sys.executable, f"experiments/{script}.py", *args],
      cwd=REPO,
      env=environ(JAX_PLATFORMS="cpu"),
      capture_output=True,
      text=True,
      timeout=timeout,
  )
