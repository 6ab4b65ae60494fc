"""Shared pytest fixtures."""

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture
def shared_dir() -> Path:
  """../shared beside the repository; skips the test where it is absent."""
  if not SHARED.is_dir():
    pytest.skip("../shared is not beside this checkout")
  return SHARED
