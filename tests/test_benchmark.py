"""experiments/benchmark.py: the reference_bench JSON and the official / ours table."""

import json

import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax.inference import sampling as sampling_lib
from cvmdx_jax.runs.config import DiffusionConfig
from cvmdx_jax.storage import atomic
from experiments import benchmark

OFFICIAL = {"params": 22_470_000, "b1": {"total": 1.6, "ddim": 1.5, "post": 0.1},
            "big": {"total": 48.0, "b": 32}, "train": {"step": 6.0, "batch": 256}}


@pytest.mark.slow
def test_reference_timings_schema_on_a_tiny_model(tmp_path):
  config = DiffusionConfig.from_config(diffusion_config.get_config("tiny"))
  sampling = sampling_lib.SamplingConfig(num_samples=3, sampler="dpmpp2m", steps=2)
  timings = benchmark.reference_timings(
      config, 4, sampling, big=3, train_batch=4,
      repeats={"b1": (1, 2), "big": (0, 1), "train": (1, 1)})
  assert timings["sampler"] == "dpmpp2m" and timings["steps"] == 2
  assert timings["big"]["b"] == 3 and timings["train"]["batch"] == 4
  assert timings["params"] > 0
  for group, field in (("b1", "total"), ("big", "total"), ("train", "step")):
    assert timings[group][field] > 0
  # what it returns is written as JSON that read_timings accepts unchanged
  atomic.write_json(tmp_path / "ours.json", timings, indent=1)
  assert benchmark.read_timings(tmp_path / "ours.json") == timings


def test_ratio_table_against_a_fake_official_json(tmp_path):
  path = tmp_path / "official.json"
  path.write_text(json.dumps(OFFICIAL))
  official = benchmark.read_timings(path)
  ours = {"b1": {"total": 0.4}, "big": {"total": 16.0, "b": 32},
          "train": {"step": 4.8, "batch": 256}}
  rows = benchmark.ratio_rows(official, ours)
  # hand-worked: 1.6 / 0.4; (48 / 32) / (16 / 32); 6.0 / 4.8
  assert [r[3] for r in rows] == pytest.approx([4.0, 3.0, 1.25])
  assert rows[1][1:3] == pytest.approx((1.5, 0.5))
  table = benchmark.ratio_table(official, ours).splitlines()
  assert len(table) == 5 and table[2].endswith("| 4.00x |") and "1.25x" in table[4]


def test_read_timings_names_the_file_and_the_missing_field(tmp_path):
  path = tmp_path / "broken.json"
  path.write_text(json.dumps({"b1": {"total": 1.0}, "big": {"b": 32}, "train": {"step": 1}}))
  with pytest.raises(ValueError, match=r"broken.json: field big.total"):
    benchmark.read_timings(path)
