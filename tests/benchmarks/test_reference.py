"""benchmarks.reference: the reference_bench JSON, the official / ours table, the table of
the performance options, the student the distilled sampler is timed on."""

import json

import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax.benchmarks import reference
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.models.performance import PerformanceOptions
from cvmdx_jax.storage import atomic

OFFICIAL = {
    "params": 22_470_000,
    "b1": {"total": 1.6, "ddim": 1.5, "post": 0.1},
    "big": {"total": 48.0, "b": 32},
    "train": {"step": 6.0, "batch": 256},
}


@pytest.mark.slow
def test_reference_timings_schema_on_a_tiny_model(tmp_path):
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("tiny"))
  sampling = SamplingConfig(num_samples=3, sampler="dpmpp2m", steps=2)
  timings = reference.reference_timings(
      config,
      4,
      sampling,
      big=3,
      train_batch=4,
      repeats={"b1": (1, 2), "big": (0, 1), "train": (1, 1)},
  )
  assert timings["sampler"] == "dpmpp2m" and timings["steps"] == 2
  assert timings["big"]["b"] == 3 and timings["train"]["batch"] == 4
  assert timings["params"] > 0
  for group, field in (("b1", "total"), ("b1", "first"), ("big", "total"), ("train", "step")):
    assert timings[group][field] > 0
  # what it returns is written as JSON that read_timings accepts unchanged
  atomic.write_json(tmp_path / "ours.json", timings, indent=1)
  assert reference.read_timings(tmp_path / "ours.json") == timings


def test_ratio_table_against_a_fake_official_json(tmp_path):
  path = tmp_path / "official.json"
  path.write_text(json.dumps(OFFICIAL))
  official = reference.read_timings(path)
  ours = {
      "b1": {"total": 0.4},
      "big": {"total": 16.0, "b": 32},
      "train": {"step": 4.8, "batch": 256},
  }
  rows = reference.ratio_rows(official, ours)
  # hand-worked: 1.6 / 0.4; (48 / 32) / (16 / 32); 6.0 / 4.8
  assert [r[3] for r in rows] == pytest.approx([4.0, 3.0, 1.25])
  assert rows[1][1:3] == pytest.approx((1.5, 0.5))
  table = reference.ratio_table(official, ours).splitlines()
  assert len(table) == 5 and table[2].endswith("| 4.00x |") and "1.25x" in table[4]
  gpu = reference.ratio_table(official, {**ours, "big": {"total": 0.0115, "b": 32}})
  assert "| 0.000359 s |" in gpu  # three significant digits at a GPU's speed


def test_read_timings_names_the_file_and_the_missing_field(tmp_path):
  path = tmp_path / "broken.json"
  path.write_text(json.dumps({"b1": {"total": 1.0}, "big": {"b": 32}, "train": {"step": 1}}))
  with pytest.raises(ValueError, match=r"broken.json: field big.total"):
    reference.read_timings(path)


def test_performance_table_marks_what_auto_takes_per_platform():
  t = {
      "b1": {"total": 0.5, "first": 20.0},
      "big": {"total": 8.0, "b": 32},
      "train": {"step": 3.0, "batch": 256},
  }
  rows = [(PerformanceOptions("on", "on"), t), (PerformanceOptions("off", "off"), t)]
  cpu = reference.performance_table(rows, "cpu").splitlines()
  assert len(cpu) == 4 and "auto on cpu" in cpu[0]
  assert cpu[2] == ("| on | on | x | 20.00 s | 0.500 s | 0.250 s (B=32) | " "3.000 s (batch 256) |")
  assert cpu[3].startswith("| off | off |  |")
  gpu = reference.performance_table(rows, "gpu").splitlines()
  assert gpu[2].startswith("| on | on |  |") and gpu[3].startswith("| off | off | x |")


def test_the_distilled_sampler_is_timed_on_a_student():
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("demo")).with_tokens(5)
  pair = SamplingConfig(sampler="dpmpp2m", steps=3)
  assert reference.sampled_config(config, pair) is config
  student = reference.sampled_config(config, SamplingConfig(sampler="distilled", steps=2))
  assert student.diffusion.guidance_input and not config.diffusion.guidance_input
  assert student.model.cond_dim == config.model.cond_dim + 1
  assert (student.sampling.sampler, student.sampling.steps) == ("distilled", 2)
