"""Data readers and the `Scenarios` contract."""

from cvmdx_jax.data.scenarios import Scenarios, concatenate, from_arrays

__all__ = ["Scenarios", "concatenate", "from_arrays"]
