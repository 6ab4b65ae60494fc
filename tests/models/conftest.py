"""The network tests compare the networks' arithmetic with references at float32 tolerances:
each runs under `float32_arithmetic` (tests/conftest.py)."""

import pytest


@pytest.fixture(autouse=True)
def _float32(float32_arithmetic):
  yield
