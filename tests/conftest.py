"""Shared pytest fixtures."""

import os
from pathlib import Path

import pytest

from cvmdx_jax import host_allocator

# Entry points started by the tests keep the allocator they start with (no re-execution,
# which would double their start-up); tests/test_host_allocator.py covers it.
os.environ[host_allocator.OPT_OUT] = "system"

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture
def shared_dir() -> Path:
  """../shared beside the repository; skips the test where it is absent."""
  if not SHARED.is_dir():
    pytest.skip("../shared is not beside this checkout")
  return SHARED
