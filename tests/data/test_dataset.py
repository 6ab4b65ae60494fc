"""dataset.build / load_split / dataset_id and the cache rules, on hand-built recordings."""

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
  with pytest.raises(DataError,
                     match=r"unknown split 'test_ood', available: \['test', 'train', 'val'\]"):
    dataset.load_split(out, "test_ood")
  path = out / "cache" / "test.npz"
  path.write_bytes(path.read_bytes()[:-10])  # interrupted write
  with pytest.raises(DataError, match="does not match metadata"):
    dataset.load_split(out, "test")


def test_missing_split_recordings(highd_config, highd_dir, tmp_path):
  config = highd_config()
  config.splits.test = (7,)
  with pytest.raises(DataError, match="empty selection") as info:
    dataset.build(config, tmp_path / "out")
  assert info.value.column == "splits.test"
  assert not (tmp_path / "out" / "cache").exists()
