"""dataset.build / load_split / dataset_id and the cache rules, on hand-built recordings."""

import json
import os

import numpy as np
import pytest

from cvmdx_jax.data import dataset
from cvmdx_jax.data.errors import DataError


def test_build_reuse_and_rebuild(highd_config, highd_dir, tmp_path):
  out = tmp_path / "out"
  splits = dataset.build(highd_config(), out)
  assert set(splits) == {"train", "val", "test"}  # test_ood = (): not built
  assert np.bincount(splits["train"].label).tolist() == [2, 2, 2]
  assert set(splits["test"].recording_id.tolist()) == {2}
  ident = dataset.dataset_id(out)
  stamp = (out / "cache" / "train.npz").stat().st_mtime_ns
  again = dataset.build(highd_config(), out)  # same settings: reused, not rewritten
  assert (out / "cache" / "train.npz").stat().st_mtime_ns == stamp
  np.testing.assert_array_equal(again["train"].xi, splits["train"].xi)
  assert dataset.dataset_id(out) == ident
  np.testing.assert_array_equal(dataset.load_split(out, "test").frame, splits["test"].frame)
  config = highd_config()
  config.extraction.lc_offsets_s = (1.0,)  # other settings: rebuilt
  assert len(dataset.build(config, out)["train"]) == 3
  assert dataset.dataset_id(out) != ident


def test_changed_source_file_rebuilds(highd_config, highd_dir, tmp_path):
  out = tmp_path / "out"
  dataset.build(highd_config(), out)
  ident = dataset.dataset_id(out)
  with open(highd_dir / "01_tracksMeta.csv", "a") as handle:
    handle.write("\n")  # size changes
  dataset.build(highd_config(), out)
  assert dataset.dataset_id(out) != ident


def test_load_split_errors(highd_config, highd_dir, tmp_path):
  out = tmp_path / "out"
  with pytest.raises(DataError, match="no dataset cache"):
    dataset.load_split(out, "train")
  dataset.build(highd_config(), out)
  with pytest.raises(
      DataError, match=r"unknown split 'test_ood', available: \['test', 'train', 'val'\]"
  ):
    dataset.load_split(out, "test_ood")
  path = out / "cache" / "test.npz"
  path.write_bytes(path.read_bytes()[:-10])  # interrupted write
  with pytest.raises(DataError, match="cache file does not match its checksum"):
    dataset.load_split(out, "test")


def test_missing_split_recordings(highd_config, highd_dir, tmp_path):
  config = highd_config()
  config.splits.test = (7,)
  with pytest.raises(DataError, match="empty selection") as info:
    dataset.build(config, tmp_path / "out")
  assert info.value.column == "splits.test"
  assert not (tmp_path / "out" / "cache").exists()


def test_same_size_edit_rebuilds(highd_config, highd_dir, tmp_path):
  out = tmp_path / "out"
  dataset.build(highd_config(), out)
  ident = dataset.dataset_id(out)
  path = highd_dir / "02_tracks.csv"
  data = path.read_bytes()
  before = path.stat()
  edited = data.replace(b",100.00,100.00,", b",101.00,100.00,", 1)  # one sight distance
  path.write_bytes(edited)
  os.utime(path, ns=(before.st_atime_ns, before.st_mtime_ns))  # size and mtime unchanged
  assert path.stat().st_size == before.st_size and edited != data
  stamp = (out / "cache" / "metadata.json").read_bytes()
  dataset.build(highd_config(), out)
  assert dataset.dataset_id(out) != ident
  assert (out / "cache" / "metadata.json").read_bytes() != stamp


def test_id_independent_of_path_spelling(highd_config, highd_dir, tmp_path, monkeypatch):
  """Absolute, relative and symlinked spellings of highd_dir and data_dir: one id, and the
  cache is reused (not rewritten)."""
  out = tmp_path / "out"
  dataset.build(highd_config(), out)
  ident = dataset.dataset_id(out)
  stamp = (out / "cache" / "train.npz").stat().st_mtime_ns
  (tmp_path / "link").symlink_to(highd_dir, target_is_directory=True)
  (tmp_path / "out_link").symlink_to(out, target_is_directory=True)
  monkeypatch.chdir(tmp_path)
  for source, data_dir in [
      (os.path.relpath(highd_dir, tmp_path), "out"),
      ("link", "out_link"),
      (str(tmp_path / "link"), "./out/../out"),
  ]:
    config = highd_config()
    config.highd_dir = source
    dataset.build(config, data_dir)
    assert dataset.dataset_id(data_dir) == ident, (source, data_dir)
  assert (out / "cache" / "train.npz").stat().st_mtime_ns == stamp


@pytest.mark.parametrize(
    "edit",
    [
        lambda m: [],
        lambda m: {},
        lambda m: "metadata",
        lambda m: {**m, "sources": [s[:2] for s in m["sources"]]},  # no sha256
        lambda m: {
            **m,
            "splits": {
                k: {x: y for x, y in v.items() if x != "count"} for k, v in m["splits"].items()
            },
        },
        lambda m: {**m, "splits": {"train": {**m["splits"]["train"], "count": "12"}}},
        lambda m: {**m, "splits": {"train": {**m["splits"]["train"], "file": "../../x.npz"}}},
        lambda m: {**m, "splits": []},
        lambda m: {**m, "settings": None},
        lambda m: {**m, "format_version": 1},
        lambda m: {**m, "sources": {"a": 1}},
    ],
)
def test_malformed_metadata_means_rebuild(highd_config, highd_dir, tmp_path, edit):
  out = tmp_path / "out"
  dataset.build(highd_config(), out)
  ident = dataset.dataset_id(out)
  path = out / "cache" / "metadata.json"
  good = json.loads(path.read_text())
  path.write_text(json.dumps(edit(good)))
  with pytest.raises(DataError, match="no dataset cache here, or a malformed"):
    dataset.load_split(out, "train")
  with pytest.raises(DataError, match="no dataset cache here, or a malformed"):
    dataset.dataset_id(out)
  splits = dataset.build(highd_config(), out)  # repairs itself
  assert json.loads(path.read_text()) == good and dataset.dataset_id(out) == ident
  assert len(splits["train"]) == 6


def test_load_balanced_takes_a_seeded_class_balanced_subset(tmp_path):
  from tests.train import baseline_data  # a cached synthetic dataset, labels 0, 1, 2, 0, ...

  baseline_data.write(tmp_path / "data", tmp_path / "tokens")
  whole = dataset.load_balanced(tmp_path / "data", "train")
  assert len(whole) == 48
  subset = dataset.load_balanced(tmp_path / "data", "train", seed=3, size=9)
  assert np.bincount(subset.label).tolist() == [3, 3, 3]
  again = dataset.load_balanced(tmp_path / "data", "train", seed=3, size=9)
  np.testing.assert_array_equal(subset.xi, again.xi)
  rows = [np.flatnonzero((whole.xi == x).all(axis=(1, 2, 3)))[0] for x in subset.xi]
  assert len(set(rows)) == 9  # nine different scenarios of the split
