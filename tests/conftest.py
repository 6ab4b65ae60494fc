"""Shared pytest fixtures."""

import importlib.util
import os
import tempfile
from pathlib import Path

import pytest

# One XLA compilation per distinct computation across the whole run (the tests build the
# same tiny models many times, in this process, in the xdist workers and in the entry points
# they start): JAX's persistent compilation cache. A user's setting wins;
# set before JAX is imported.
os.environ.setdefault(
    "JAX_COMPILATION_CACHE_DIR", str(Path(tempfile.gettempdir()) / f"cvmdx_jax_tests_{os.getuid()}")
)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.2")

from cvmdx_jax import host_allocator  # noqa: E402

# Entry points started by the tests keep the allocator they start with (no re-execution,
# which would double their start-up); tests/test_host_allocator.py covers it.
os.environ[host_allocator.OPT_OUT] = "system"

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
REQUIRE_SUMO = "CVMDX_REQUIRE_SUMO"  # "1" (`make test`): a missing eclipse-sumo fails the tests


@pytest.fixture
def shared_dir() -> Path:
  """../shared beside the repository; skips the test where it is absent."""
  if not SHARED.is_dir():
    pytest.skip("../shared is not beside this checkout")
  return SHARED


@pytest.fixture
def float32_arithmetic():
  """Runs a test in true float32 on every backend. By default XLA computes float32
  convolutions and products on NVIDIA GPUs in TF32, as PyTorch's cuDNN does, and the library
  keeps that default for its networks (`constants.EXACT_MATMUL`); tests of the networks'
  arithmetic against float32 tolerances ask for this. No effect on a CPU."""
  import jax  # here: the environment above is set before JAX is imported

  with jax.default_matmul_precision("float32"):
    yield


@pytest.fixture(scope="session")
def eclipse_sumo():
  """For tests that simulate: skips them where eclipse-sumo is not installed (a GPU host that
  reads highD), fails them instead where CVMDX_REQUIRE_SUMO=1 (`make test`, which installs it)."""
  if importlib.util.find_spec("sumo") is None:
    message = "eclipse-sumo is not installed (pip install eclipse-sumo)"
    if os.environ.get(REQUIRE_SUMO) == "1":
      pytest.fail(f"{message}, and {REQUIRE_SUMO}=1")
    pytest.skip(message)


@pytest.fixture(scope="session")
def scenarios_factory():
  """`make_scenarios(m, seed=0)` of tests/models/tokenizer_data.py: toy scenarios of three
  maneuver classes for the tokeniser's model and trainer tests."""
  from tests.models import tokenizer_data

  return tokenizer_data.make_scenarios


@pytest.fixture(scope="session")
def tiny_runs(tmp_path_factory, request, eclipse_sumo) -> Path:
  """Root of tiny trained runs (data/, tokenizer/, diffusion/: tests/fixtures_runs.py), built
  once per session; under xdist once for all workers (in the run's shared temp directory).
  Read-only: tests write into their own `tmp_path`."""
  from tests import fixtures_runs

  shared = hasattr(request.config, "workerinput")  # an xdist worker
  base = tmp_path_factory.getbasetemp()
  return fixtures_runs.build((base.parent if shared else base) / "tiny_runs")
