"""train / val / test / test_ood splits for every source: disjoint by recording, val present,
the held-out road unseen in training, and the tokeniser picking up every split."""

import numpy as np
import pandas as pd
import pytest

from configs import dataset as dataset_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.data import cache, cvmd_mat, dataset, highd, sumo_plan
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.train import tokenizer as tokenizer_train


def test_highd_split_is_the_documented_one():
  c = dataset_config.get_config()
  train, val, test = (set(c.splits[k]) for k in ("train", "val", "test"))
  assert test == {3, 6, 9, 13, 16, 19, 23, 26, 29, 33, 36, 39, 43, 46, 49, 53, 56, 59}
  assert val == {10, 20, 30, 40, 50, 60}
  assert not (train & val or train & test or val & test)
  assert train | val | test == set(range(1, 61)) and len(train) == 36
  assert tuple(c.splits.test_ood) == ()


def test_highd_recording_in_two_splits_is_refused(highd_config, tmp_path):
  config = highd_config()
  config.splits.val = (1,)
  with pytest.raises(DataError, match="recording 1 is in both train and val") as info:
    dataset.build(config, tmp_path / "out")
  assert info.value.column == "splits.val"
  assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("split", ["train", "val", "test"])
def test_highd_split_whose_recordings_are_all_missing_is_refused(highd_config, tmp_path, split):
  config = highd_config()
  config.splits[split] = (7,)  # no recording 7 in highd_dir
  with pytest.raises(DataError, match=f"empty selection: none of the {split} recordings") as info:
    dataset.build(config, tmp_path / "out")
  assert info.value.column == f"splits.{split}"
  assert f"give it no ids: --config.splits.{split}=()" in str(info.value)
  assert not (tmp_path / "out" / "cache").exists()


def test_highd_test_only_dataset_for_a_trained_model(highd_config, tmp_path):
  """Recordings of a road never seen, all in test: only test is built; a trainer asking for
  train gets a DataError naming the splits there."""
  config = highd_config()
  config.splits.train, config.splits.val, config.splits.test = (), (), (1, 2, 3)
  splits = dataset.build(config, tmp_path / "out")
  assert list(splits) == ["test"]
  assert sorted(set(splits["test"].recording_id.tolist())) == [1, 2, 3]
  assert dataset.split_names(tmp_path / "out") == ["test"]
  np.testing.assert_array_equal(
      dataset.load_split(tmp_path / "out", "test").label, splits["test"].label
  )
  with pytest.raises(DataError, match=r"unknown split 'train', available: \['test'\]"):
    dataset.load_split(tmp_path / "out", "train")


def test_highd_no_split_at_all_is_refused(highd_config, tmp_path):
  config = highd_config()
  config.splits.train, config.splits.val, config.splits.test = (), (), ()
  with pytest.raises(DataError, match="empty selection: no split has a recording") as info:
    dataset.build(config, tmp_path / "out")
  assert info.value.column == "splits"
  assert not (tmp_path / "out" / "cache").exists()


def test_highd_test_ood_and_val_ood_are_built_when_given(highd_config, highd_dir, tmp_path):
  from tests.data.conftest import write_recording

  write_recording(highd_dir, 4)
  write_recording(highd_dir, 5)
  config = highd_config()
  config.splits.test_ood = (4,)
  splits = dataset.build(config, tmp_path / "out")
  assert list(splits) == ["train", "val", "test", "test_ood"]
  assert {k: sorted(set(v.recording_id.tolist())) for k, v in splits.items()} == {
      "train": [1],
      "val": [3],
      "test": [2],
      "test_ood": [4],
  }
  assert dataset.split_names(tmp_path / "out") == ["train", "val", "test", "test_ood"]
  config.splits.val_ood = (5,)
  splits = dataset.build(config, tmp_path / "out")
  assert sorted(set(splits["val_ood"].recording_id.tolist())) == [5]
  assert dataset.split_names(tmp_path / "out") == ["train", "val", "test", "test_ood", "val_ood"]
  config.splits.val_ood = (4,)  # a recording in two splits
  with pytest.raises(DataError, match="recording 4 is in both test_ood and val_ood"):
    dataset.build(config, tmp_path / "out")


def test_mat_val_index_is_stratified_and_seeded():
  labels = np.repeat([0, 1, 2], [40, 20, 7])
  index = dataset.mat_val_index(labels, 0.15, seed=0)
  assert np.bincount(labels[index], minlength=3).tolist() == [6, 3, 1]  # round(0.15 n)
  assert len(np.unique(index)) == len(index) and np.all(np.diff(index) > 0)
  np.testing.assert_array_equal(index, dataset.mat_val_index(labels, 0.15, seed=0))
  assert not np.array_equal(index, dataset.mat_val_index(labels, 0.15, seed=1))


def test_cvmd_mat_val_is_carved_from_train(highd_config, tmp_path):
  scen = dataset.build(highd_config(), tmp_path / "h")
  for name, s in (("train", scen["train"]), ("test", scen["test"])):
    cvmd_mat.export(s, tmp_path / "mat" / name)
  config = highd_config()
  config.source, config.mat_dir, config.mat_val_fraction = "cvmd_mat", str(tmp_path / "mat"), 0.5
  splits = dataset.build(config, tmp_path / "out")
  assert list(splits) == ["train", "val", "test"]
  assert np.bincount(splits["val"].label).tolist() == [1, 1, 1]  # round(0.5 * 2) per class
  assert np.bincount(splits["train"].label).tolist() == [1, 1, 1]
  # Together they are the train files, each once; test is untouched.
  pooled = np.concatenate([splits["train"].future, splits["val"].future])
  reference = cvmd_mat.load(tmp_path / "mat" / "train").future
  assert sorted(map(bytes, pooled)) == sorted(map(bytes, reference))
  np.testing.assert_array_equal(
      splits["test"].future, cvmd_mat.load(tmp_path / "mat" / "test").future
  )
  config.mat_val_fraction = 0.1  # round(0.1 * 2) = 0 files per class: no val
  with pytest.raises(DataError, match="mat_val_fraction"):
    dataset.build(config, tmp_path / "out2")


def test_tokenizer_tokenises_every_cached_split(highd_config, tmp_path):
  splits = dataset.build(highd_config(), tmp_path / "out")
  renamed = {
      "train": splits["train"],
      "val": splits["val"],
      "test": splits["test"],
      "test_ood": splits["test"],
  }
  meta = cache.read_metadata(tmp_path / "out" / "cache")
  cache.write(tmp_path / "out" / "cache", renamed, meta["settings"], meta["sources"])
  config = tokenizer_config.get_config("tiny")
  config.data_dir = str(tmp_path / "out")
  loaded, _ = tokenizer_train._load_splits(config)
  assert list(loaded) == ["train", "val", "test", "test_ood"]
  config.splits = ("train", "test")
  assert list(tokenizer_train._load_splits(config)[0]) == ["train", "test"]


@pytest.mark.usefixtures("eclipse_sumo")
def test_sumo_tiny_splits_by_recording_and_held_out_road(tmp_path):
  config = dataset_config.get_config("tiny")
  config.sumo.duration_s = config.sumo.held_out.duration_s = 30.0
  config.extraction.balance = False
  splits = dataset.build(config, tmp_path)
  ids = sumo_plan.split_ids(config.sumo)
  assert list(splits) == [name for name in ids if ids[name]] == ["train", "val", "test", "test_ood"]
  for name, s in splits.items():
    assert len(s) > 0 and set(s.recording_id.tolist()) <= set(ids[name]), name

  def road(rid):  # (lanes per direction, lane width) from the written markings
    meta = pd.read_csv(highd.recording_paths(tmp_path / "recordings", rid)["recordingMeta"])
    upper = np.array([float(v) for v in meta.upperLaneMarkings[0].split(";")])
    return len(upper) - 1, round(float(np.diff(upper).mean()), 2), round(meta.speedLimit[0], 2)

  train_roads = {road(r) for r in ids["train"] + ids["val"] + ids["test"]}
  ood_roads = {road(r) for r in ids["test_ood"]}
  assert {r[0] for r in train_roads} == {2, 3} and {r[1] for r in train_roads} == {3.75}
  assert ood_roads == {(4, 3.5, 30.56)} and not ood_roads & train_roads


@pytest.mark.usefixtures("eclipse_sumo")
def test_sumo_road_of_ones_own_as_a_test_ood_only_dataset(tmp_path):
  """0 recordings for train, val, test and val_ood: only test_ood is simulated and built, on
  the road given in `sumo.held_out` (read back from the written lane markings)."""
  config = dataset_config.get_config("tiny")
  for name in ("train", "val", "test", "val_ood"):
    config.sumo.recordings[name] = 0
  config.sumo.held_out.update(lanes=2, lane_width_m=3.25, speed_limit_kmh=80.0, duration_s=30.0)
  config.extraction.balance = False
  splits = dataset.build(config, tmp_path)
  assert list(splits) == ["test_ood"] and len(splits["test_ood"]) > 0
  assert dataset.split_names(tmp_path) == ["test_ood"]
  assert set(splits["test_ood"].recording_id.tolist()) == {1}
  assert highd.available_recordings(tmp_path / "recordings") == [1]
  meta = pd.read_csv(highd.recording_paths(tmp_path / "recordings", 1)["recordingMeta"])
  upper = np.array([float(v) for v in meta.upperLaneMarkings[0].split(";")])
  assert len(upper) - 1 == 2 and np.allclose(np.diff(upper), 3.25)
  assert meta.speedLimit[0] == pytest.approx(80.0 / 3.6, abs=0.01)


def test_sumo_no_recording_at_all_is_refused_before_simulating(tmp_path):
  config = dataset_config.get_config("tiny")
  for name in sumo_plan.SPLITS:
    config.sumo.recordings[name] = 0
  with pytest.raises(DataError, match="empty selection: no split has a recording") as info:
    dataset.build(config, tmp_path / "out")
  assert info.value.column == "sumo.recordings"
  assert not (tmp_path / "out").exists()
