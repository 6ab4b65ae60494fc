"""The functional form of an NNX model: (graphdef, params) with params a pure dict.

Every model (`unet1d`, `tokenizer`, `multiple_choice`, `mdn`) is used this way: `init_*`
builds the model and returns its graph definition and the pure dict of its `nnx.Param`
leaves (`nnx.split(model, nnx.Param)`), `make_graphdef` and `abstract_params` give the graph
definition and the parameters' shapes without allocating parameters, and `apply_*` merges
the two inside a jitted function. Train states and checkpoints hold these pure dicts.

The abstract build traces every initialiser of the model (~0.7 s for the demo's U-Net on a
2-core CPU), so it runs once per model class and config in a process: a run directory read
again (the teacher of two students, the tokeniser of every stage) costs no second build.
"""

import functools
from collections.abc import Callable

import jax
from flax import nnx

Build = Callable[[nnx.Rngs], nnx.Module]  # rngs -> model


def init(build: Build, key: jax.Array) -> tuple[nnx.GraphDef, dict]:
  """(graphdef, params) of `build(nnx.Rngs(params=key))`."""
  graphdef, params = nnx.split(build(nnx.Rngs(params=key)), nnx.Param)
  return graphdef, nnx.to_pure_dict(params)


@functools.lru_cache(maxsize=32)
def _abstract(model_cls: type[nnx.Module], config) -> tuple[nnx.GraphDef, dict]:
  """(graphdef, params as ShapeDtypeStructs) of `model_cls(config, rngs=...)`, built once."""
  model = nnx.eval_shape(lambda: model_cls(config, rngs=nnx.Rngs(0)))
  graphdef, params = nnx.split(model, nnx.Param)
  return graphdef, nnx.to_pure_dict(params)


def make_graphdef(model_cls: type[nnx.Module], config) -> nnx.GraphDef:
  """The graph definition of `model_cls(config, rngs=...)` (config hashable: a frozen
  dataclass); no parameters are allocated."""
  return _abstract(model_cls, config)[0]


def abstract_params(model_cls: type[nnx.Module], config) -> dict:
  """The pure dict of `model_cls(config, rngs=...)`'s parameters as `jax.ShapeDtypeStruct`s
  (a new dict each call; nothing is allocated)."""
  return jax.tree.map(lambda x: x, _abstract(model_cls, config)[1])
