"""The package's run-time imports: scikit-learn and the tests stay out of it."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_IMPORT_ALL = """
import importlib, pkgutil, sys
import cvmdx_jax
names = [m.name for m in pkgutil.walk_packages(cvmdx_jax.__path__, "cvmdx_jax.")]
for name in names:
  importlib.import_module(name)
assert "cvmdx_jax.evaluation.report" in names
print(sorted({n.split(".")[0] for n in sys.modules if n.split(".")[0] in ("sklearn", "tests")}))
"""


def test_no_module_of_the_package_imports_sklearn_or_tests():
  env = {**os.environ, "PYTHONPATH": str(REPO), "JAX_PLATFORMS": "cpu"}
  proc = subprocess.run([sys.executable, "-c", _IMPORT_ALL], cwd=REPO, env=env,
                        capture_output=True, text=True, timeout=600)
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert proc.stdout.strip().splitlines()[-1] == "[]"
