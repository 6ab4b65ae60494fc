"""The checks of a checkpoint's pytree before it is used: leaves, shapes and dtypes against
the expected state (`check_structure`), and no NaN in any leaf (`refuse_nan`); each refusal
is a `CheckpointMismatchError` naming the leaf."""

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.errors import UserError


class CheckpointMismatchError(UserError):
  """A checkpoint is missing, unreadable, or does not belong to the requested run."""


def _path_key(path: tuple[Any, ...]) -> str:
  """A tree path as 'a/0/b', the same for a namedtuple field and orbax's dict key."""
  parts = []
  for p in path:
    for attr in ("key", "idx", "name"):
      if hasattr(p, attr):
        parts.append(str(getattr(p, attr)))
        break
    else:
      parts.append(str(p))
  return "/".join(parts)


def _leaf_specs(tree: Any) -> dict[str, tuple[tuple[int, ...], str]]:
  leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
  return {_path_key(p): (tuple(x.shape), np.dtype(x.dtype).name) for p, x in leaves}


def check_structure(
    saved_meta: Any, abstract_state: Any, where: str, partial: bool = False
) -> None:
  """Raises CheckpointMismatchError when leaves, shapes or dtypes differ, naming the leaf.

  With `partial`, leaves of the checkpoint that `abstract_state` lacks are allowed.
  """
  saved, want = _leaf_specs(saved_meta), _leaf_specs(abstract_state)
  problems = []
  for k in sorted(set(saved) | set(want)):
    if k not in saved:
      problems.append(f"leaf {k!r} expected {want[k][0]} but absent from the checkpoint")
    elif k not in want:
      if partial:
        continue
      problems.append(f"leaf {k!r} {saved[k][0]} in the checkpoint but not expected")
    elif saved[k] != want[k]:
      problems.append(
          f"leaf {k!r}: checkpoint shape {saved[k][0]} {saved[k][1]}, "
          f"expected shape {want[k][0]} {want[k][1]}"
      )
  if problems:
    raise CheckpointMismatchError(
        f"checkpoint {where} does not match the expected state (other model size?): "
        + "; ".join(problems[:8])
        + (f"; ... {len(problems) - 8} more" if len(problems) > 8 else "")
    )


def _holds_nan(leaf: Any) -> bool:
  """Whether a leaf holds a NaN in the data this process holds (one copy of each shard;
  non-float leaves: False). On the host: a jitted check compiles per tree structure, ~0.7 s a
  checkpoint on a 2-core CPU, for parameters this small to copy."""
  if not jnp.issubdtype(leaf.dtype, jnp.inexact):
    return False
  if isinstance(leaf, jax.Array):
    return any(
        np.isnan(np.asarray(s.data)).any() for s in leaf.addressable_shards if s.replica_id == 0
    )
  return bool(np.isnan(np.asarray(leaf)).any())


def refuse_nan(state: Any, where: Path) -> None:
  """CheckpointMismatchError naming the first leaf of `state` that holds a NaN (weights of a
  diverged run: never loaded, neither to resume nor as a teacher). Infinities pass (a
  best-so-far score starts at inf)."""
  flat = jax.tree_util.tree_flatten_with_path(state)[0]
  bad = next((path for path, leaf in flat if _holds_nan(leaf)), None)
  if bad is not None:
    raise CheckpointMismatchError(
        f"checkpoint {where} holds NaN in {_path_key(bad)!r} (a diverged run): "
        "delete this step directory to fall back to an older one, or retrain"
    )
