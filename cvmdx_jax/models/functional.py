"""The functional form of an NNX model: (graphdef, params) with params a pure dict.

Both models (`unet1d`, `tokenizer`) are used this way: `init_*` builds the model and
returns its graph definition and the pure dict of its `nnx.Param` leaves
(`nnx.split(model, nnx.Param)`), `make_graphdef` gives the graph definition without
allocating parameters, and `apply_*` merges the two inside a jitted function. Train
states and checkpoints hold these pure dicts.
"""

from collections.abc import Callable

import jax
from flax import nnx

Build = Callable[[nnx.Rngs], nnx.Module]  # rngs -> model


def init(build: Build, key: jax.Array) -> tuple[nnx.GraphDef, dict]:
  """(graphdef, params) of `build(nnx.Rngs(params=key))`."""
  graphdef, params = nnx.split(build(nnx.Rngs(params=key)), nnx.Param)
  return graphdef, nnx.to_pure_dict(params)


def make_graphdef(build: Build) -> nnx.GraphDef:
  """The graph definition of `build`'s model; no parameters are allocated."""
  return nnx.split(nnx.eval_shape(lambda: build(nnx.Rngs(0))), nnx.Param)[0]
