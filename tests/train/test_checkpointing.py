"""Tests of cvmdx_jax.storage.checkpointing and storage.identity: round trips and the mismatch
errors users see."""

import logging
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from cvmdx_jax import sharding
from cvmdx_jax.storage import checkpointing, checksums, identity
from cvmdx_jax.storage.checkpointing import CheckpointMismatchError


def _state(width: int = 3):
  params = {"w": jnp.arange(2.0 * width).reshape(2, width), "b": [jnp.ones(width)]}
  return {"params": params, "opt": optax.adam(1e-3).init(params), "n": jnp.int32(7)}


def _abstract(state):
  rep = sharding.replicated(sharding.data_mesh())
  return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep), state)


def test_round_trip_keeps_structure_values_and_metadata(tmp_path):
  state = _state()
  with checkpointing.Checkpoints(tmp_path, keep=2) as ckpts:
    for step in (1, 2, 3):
      ckpts.save(step, state, {"q": step, "dims": (2, 3)})
    assert ckpts.latest_epoch == 3
  assert sorted(p.name for p in tmp_path.iterdir()) == ["2", "3"]  # keep=2
  restored, meta = checkpointing.Checkpoints(tmp_path, writable=False).load(3, _abstract(state))
  assert meta == {"q": 3, "dims": [2, 3]}
  assert jax.tree.structure(restored) == jax.tree.structure(state)  # namedtuples survive
  for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state)):
    np.testing.assert_array_equal(a, b)


def test_partial_load_reads_only_the_requested_leaves(tmp_path):
  state = _state()
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, state, {"q": 1})
  absl_filters = list(logging.getLogger("absl").filters)
  wanted = {"params": _abstract(state)["params"]}
  restored, meta = checkpointing.load_latest(tmp_path, wanted, partial=True)
  assert set(restored) == {"params"} and meta == {"q": 1}
  np.testing.assert_array_equal(restored["params"]["w"], state["params"]["w"])
  with pytest.raises(CheckpointMismatchError, match="'opt/0/count'.*not expected"):
    checkpointing.load_latest(tmp_path, wanted)  # a full load wants every leaf
  wider = {"params": _abstract(_state(4))["params"]}
  with pytest.raises(CheckpointMismatchError, match=r"params/w.*\(2, 3\).*\(2, 4\)"):
    checkpointing.load_latest(tmp_path, wider, partial=True)
  # orbax's log filter is installed only while orbax runs
  assert logging.getLogger("absl").filters == absl_filters


def test_identity_check_names_every_differing_key():
  saved = {"model": {"q": 60, "latent": 16}, "dataset": "sumo-a", "scale": [4.0, 0.7]}
  identity.check(
      saved, {"dataset": "sumo-a", "model": {"latent": 16, "q": 60}, "scale": (4.0, 0.7)}, "ck"
  )  # tuples compare as JSON lists
  with pytest.raises(CheckpointMismatchError) as e:
    identity.check(
        saved,
        {"model": {"q": 90, "latent": 16}, "dataset": "highd", "extra": 1, "scale": [4.0, 0.7]},
        "ck/5",
        CheckpointMismatchError,
    )
  msg = str(e.value)
  assert "ck/5" in msg and "model.q: saved 60, expected 90" in msg
  assert "dataset: saved 'sumo-a', expected 'highd'" in msg and "extra" in msg
  assert "latent" not in msg


def test_check_structure_names_leaf_and_both_shapes():
  with pytest.raises(CheckpointMismatchError, match=r"params/w.*\(2, 3\).*\(2, 5\)"):
    checkpointing.check_structure(_state(3), _abstract(_state(5)), "ck")
  missing = _state()
  del missing["n"]
  with pytest.raises(CheckpointMismatchError, match="leaf 'n'"):
    checkpointing.check_structure(missing, _abstract(_state()), "ck")


def test_fingerprint_must_be_json():
  with pytest.raises(ValueError, match="fingerprint must be JSON"):
    identity.to_json({"f": object()})


def test_content_id_covers_paths_dtypes_shapes_and_bytes():
  a = {"w": np.arange(6, dtype=np.float32).reshape(2, 3), "n": 3}
  same = {"n": 3, "w": jnp.arange(6, dtype=jnp.float32).reshape(2, 3)}  # key order, jax array
  assert identity.content_id(a) == identity.content_id(same)
  assert len(identity.content_id(a)) == 64
  for other in (
      {**a, "w": a["w"].reshape(3, 2)},
      {**a, "w": a["w"].astype(np.float64)},
      {**a, "n": 4},
      {"v": a["w"], "n": 3},
      {**a, "w": a["w"] + 1},
  ):
    assert identity.content_id(other) != identity.content_id(a)


def test_load_of_missing_step_and_garbled_checkpoint(tmp_path):
  state = _state()
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, state, {})
  reader = checkpointing.Checkpoints(tmp_path, writable=False)
  with pytest.raises(CheckpointMismatchError, match="no complete checkpoint"):
    reader.load(2, _abstract(state))
  arrays = [
      f for f in (tmp_path / "1" / "state").rglob("*") if f.is_file() and f.parent.name == "d"
  ]
  assert arrays
  for f in arrays:  # the array data only: metadata still reads, the load fails
    f.write_bytes(f.read_bytes()[: len(f.read_bytes()) // 2])
  with pytest.raises(CheckpointMismatchError, match=f"checkpoint {tmp_path / '1'} is corrupt"):
    reader.load(1, _abstract(state))
  (tmp_path / "1" / "state" / "_METADATA").write_text("{not json")
  with pytest.raises(CheckpointMismatchError, match=f"checkpoint {tmp_path / '1'} is corrupt"):
    reader.load(1, _abstract(state))


def test_relative_root_works(tmp_path, monkeypatch):
  """Users pass relative workdirs (runs/demo/...); orbax itself needs absolute paths."""
  monkeypatch.chdir(tmp_path)
  state = _state()
  with checkpointing.Checkpoints("runs/x/checkpoints", keep=1) as ckpts:
    ckpts.save(1, state, {"q": 1})
  restored, _ = checkpointing.Checkpoints("runs/x/checkpoints", writable=False).load(
      1, _abstract(state)
  )
  np.testing.assert_array_equal(restored["params"]["w"], state["params"]["w"])


def _orbax_records(caplog):
  return [r for r in caplog.records if "orbax" in r.pathname and r.levelno >= logging.WARNING]


def test_a_failed_save_leaves_no_temporary_directory_and_no_orbax_errors(
    tmp_path, monkeypatch, caplog
):
  from orbax.checkpoint._src.path import atomicity  # the rename that commits a step

  state = _state()
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, state, {"q": 1})

    async def disk_full(self):
      raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomicity.AtomicRenameTemporaryPath, "finalize", disk_full)
    caplog.set_level(logging.WARNING)
    with pytest.raises(Exception, match="No space left on device"):
      ckpts.save(2, state, {"q": 2})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["1"]
    assert _orbax_records(caplog) == []
    assert ckpts.latest_epoch == 1
    with pytest.raises(ValueError, match="an earlier save failed"):
      ckpts.save(3, state, {"q": 3})
  restored, meta = checkpointing.Checkpoints(tmp_path, writable=False).load(1, _abstract(state))
  assert meta == {"q": 1}


def test_opening_for_writing_removes_stale_temporary_directories(tmp_path):
  stale = tmp_path / "4.orbax-checkpoint-tmp-1733000000"
  (stale / "state").mkdir(parents=True)
  (stale / "state" / "x").write_bytes(b"half")
  keep = tmp_path / "notes.orbax"  # not orbax's temporary mark: left alone
  keep.write_text("mine")
  checkpointing.Checkpoints(tmp_path, writable=False)
  assert stale.is_dir()
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    assert ckpts.latest_epoch is None
  assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.orbax"]


def test_a_kill_between_commit_and_manifest_resumes_from_the_step_before(tmp_path):
  """The manifest is written after orbax commits a step: a step with the commit marker but no
  checksums.json was cut short. Reading refuses it; opening to write drops it."""
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    ckpts.save(1, _state(), {"step": 1})
    ckpts.save(2, _state(), {"step": 2})
  (tmp_path / "2" / checksums.MANIFEST).unlink()
  assert (tmp_path / "2" / "commit_success.txt").is_file()  # orbax had committed it
  with pytest.raises(CheckpointMismatchError, match="no checksums.json"):
    checkpointing.load_latest(tmp_path, _abstract(_state()))
  with checkpointing.Checkpoints(tmp_path) as ckpts:
    assert ckpts.latest_epoch == 1
  assert sorted(p.name for p in tmp_path.iterdir()) == ["1"]
  _, meta = checkpointing.load_latest(tmp_path, _abstract(_state()))
  assert meta == {"step": 1}


def test_metadata_is_read_once_per_step_content(tmp_path, monkeypatch):
  """orbax's metadata (every array opened) is read once for a step however often it is
  loaded; a step saved again with other values is read again; each caller gets its own
  metadata dict."""
  calls = []
  real = checkpointing.ocp.metadata
  monkeypatch.setattr(
      checkpointing.ocp, "metadata", lambda *a, **k: calls.append(a) or real(*a, **k)
  )
  state = _state()
  with checkpointing.Checkpoints(tmp_path / "a") as ckpts:
    ckpts.save(1, state, {"q": [1]})
  reader = checkpointing.Checkpoints(tmp_path / "a", writable=False)
  _, meta = reader.load(1, _abstract(state))
  meta["q"].append(2)  # the caller's copy
  restored, meta = reader.load(1, _abstract(state))
  assert (len(calls), meta) == (1, {"q": [1]})
  other = jax.tree.map(lambda x: x + 1, state)
  for step_dir in (tmp_path / "a").iterdir():
    shutil.rmtree(step_dir)
  with checkpointing.Checkpoints(tmp_path / "a") as ckpts:
    ckpts.save(1, other, {"q": [1]})
  restored, _ = checkpointing.Checkpoints(tmp_path / "a", writable=False).load(1, _abstract(state))
  assert len(calls) == 2
  np.testing.assert_array_equal(restored["params"]["w"], other["params"]["w"])
