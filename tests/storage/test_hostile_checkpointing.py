"""A checkpoint save that fails on a full disk leaves no orbax temporary directory behind,
also when one of orbax's background threads (the one that writes `_sharding`) still
writes after the error has surfaced; the step before stays loadable."""

import asyncio
import errno
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest
from orbax.checkpoint._src.metadata import array_metadata_store
from orbax.checkpoint._src.serialization import jax_array_handlers

from cvmdx_jax import sharding
from cvmdx_jax.storage import checkpointing


def _state():
  return {"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.ones(3)}


def _abstract(state):
  rep = sharding.replicated(sharding.data_mesh())
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep), state)


# orbax's event loop, closed by the failed save, reports the late writer's end as unraisable
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
@pytest.mark.parametrize("late_s", [0.0, 0.5])
def test_a_save_failing_on_a_full_disk_leaves_no_temporary_directory(tmp_path, monkeypatch, late_s):
  late_writes = []

  async def late_sharding_writer(shardings, infos, *args, **kwargs):
    """orbax's `_sharding` writer, late: it writes after the save's error surfaced."""
    await asyncio.sleep(late_s)
    for info in infos:
      await info.await_path_creation()
      path = Path(info.parent_dir.as_posix()) / "_sharding"
      path.mkdir(parents=True, exist_ok=True)
      (path / "late").write_text("x")
      late_writes.append(path)

  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, _state(), {"q": 1})
    monkeypatch.setattr(jax_array_handlers, "_async_serialize_shardings", late_sharding_writer)

    async def full_disk(self, *args, **kwargs):
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(array_metadata_store.Store, "write", full_disk)
    with pytest.raises(Exception, match="No space left on device"):
      ckpts.save(2, _state(), {"q": 2})
  assert late_writes  # the late writer ran, and its directory was removed after it
  assert sorted(p.name for p in tmp_path.iterdir()) == ["1"]
  _, meta = checkpointing.load_latest(tmp_path, _abstract(_state()))
  assert meta == {"q": 1}


def test_a_checkpoint_holding_nan_is_refused_naming_the_leaf(tmp_path):
  """A diverged run's weights: never resumed from, never distilled from. An infinity
  passes (a best-so-far score starts at inf)."""
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, {"w": jnp.ones(3), "best": jnp.asarray(jnp.inf)}, {"q": 1})
    ckpts.save(2, {"w": jnp.asarray([1.0, jnp.nan, 2.0]), "best": jnp.asarray(1.0)}, {"q": 2})
  abstract = _abstract({"w": jnp.ones(3), "best": jnp.asarray(1.0)})
  with pytest.raises(
      checkpointing.CheckpointMismatchError, match=r"checkpoint .*/2 holds NaN in 'w'"
  ):
    checkpointing.load_latest(tmp_path, abstract)
  state, meta = checkpointing.Checkpoints(tmp_path, writable=False).load(1, abstract)
  assert meta == {"q": 1} and float(state["best"]) == float("inf")
