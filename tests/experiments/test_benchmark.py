"""experiments/benchmark.py: the reference_bench JSON and the official / ours table, the
first-call timing, the performance options of a run and their table."""

import json

import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax import ego_motion
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.models.performance import PerformanceOptions
from cvmdx_jax.storage import atomic
from experiments import benchmark

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
  timings = benchmark.reference_timings(
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
  assert benchmark.read_timings(tmp_path / "ours.json") == timings


def test_train_timing_feeds_the_conditioning_and_labels_of_the_demo_denoiser():
  base = diffusion_config.get_config("tiny")  # with the demo's conditioning
  base.diffusion.conditioning, base.diffusion.intent_conditioning = "ego_film_residual", True
  config = DiffusionRunConfig.from_config(base).with_tokens(4)
  assert config.model.cond_dim > ego_motion.NUM_FEATURES and config.model.num_intents == 3
  assert benchmark.train_timing(config, batch=4, repeats=1) > 0


def test_ratio_table_against_a_fake_official_json(tmp_path):
  path = tmp_path / "official.json"
  path.write_text(json.dumps(OFFICIAL))
  official = benchmark.read_timings(path)
  ours = {
      "b1": {"total": 0.4},
      "big": {"total": 16.0, "b": 32},
      "train": {"step": 4.8, "batch": 256},
  }
  rows = benchmark.ratio_rows(official, ours)
  # hand-worked: 1.6 / 0.4; (48 / 32) / (16 / 32); 6.0 / 4.8
  assert [r[3] for r in rows] == pytest.approx([4.0, 3.0, 1.25])
  assert rows[1][1:3] == pytest.approx((1.5, 0.5))
  table = benchmark.ratio_table(official, ours).splitlines()
  assert len(table) == 5 and table[2].endswith("| 4.00x |") and "1.25x" in table[4]
  gpu = benchmark.ratio_table(official, {**ours, "big": {"total": 0.0115, "b": 32}})
  assert "| 0.000359 s |" in gpu  # three significant digits at a GPU's speed


def test_read_timings_names_the_file_and_the_missing_field(tmp_path):
  path = tmp_path / "broken.json"
  path.write_text(json.dumps({"b1": {"total": 1.0}, "big": {"b": 32}, "train": {"step": 1}}))
  with pytest.raises(ValueError, match=r"broken.json: field big.total"):
    benchmark.read_timings(path)


def test_time_calls_reports_the_first_call_apart_from_the_median(monkeypatch):
  clock = {"now": 0.0}
  durations = iter([9.0, 1.0, 3.0, 2.0])  # a compiling first call, then warm calls

  def call():
    clock["now"] += next(durations)

  monkeypatch.setattr(benchmark.time, "perf_counter", lambda: clock["now"])
  assert benchmark.time_calls(call, repeats=3, warmup=1) == (9.0, 2.0)
  durations = iter([4.0, 1.0])
  assert benchmark.time_calls(call, repeats=2, warmup=0) == (4.0, 2.5)  # first also timed


def test_predict_line():
  line = benchmark.predict_line(" dpmpp2m(3)", 1, 0.25, gflop=10.0, first=12.345)
  assert line == (
      "predict  B=   1 dpmpp2m(3):    0.250 s/call     250.0 ms/scenario      4.0 "
      "scenarios/s    40.0 GFLOP/s  (first call 12.35 s: trace, compile, run)"
  )
  assert benchmark.predict_line("", 16, 2.0).endswith("8.0 scenarios/s")


def test_run_options_and_the_combinations():
  env = PerformanceOptions("off", "auto")
  assert benchmark.run_options(None, env) == env and benchmark.run_options("all", env) == env
  assert benchmark.run_options("on", env) == PerformanceOptions("on", "on")
  assert len(set(benchmark.OPTION_COMBINATIONS)) == 4
  assert {"on", "off"} == {o.winograd for o in benchmark.OPTION_COMBINATIONS}


def test_performance_table_marks_what_auto_takes_per_platform():
  t = {
      "b1": {"total": 0.5, "first": 20.0},
      "big": {"total": 8.0, "b": 32},
      "train": {"step": 3.0, "batch": 256},
  }
  rows = [(PerformanceOptions("on", "on"), t), (PerformanceOptions("off", "off"), t)]
  cpu = benchmark.performance_table(rows, "cpu").splitlines()
  assert len(cpu) == 4 and "auto on cpu" in cpu[0]
  assert cpu[2] == ("| on | on | x | 20.00 s | 0.500 s | 0.250 s (B=32) | " "3.000 s (batch 256) |")
  assert cpu[3].startswith("| off | off |  |")
  gpu = benchmark.performance_table(rows, "gpu").splitlines()
  assert gpu[2].startswith("| on | on |  |") and gpu[3].startswith("| off | off | x |")


def test_the_distilled_sampler_is_timed_on_a_student():
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("demo")).with_tokens(5)
  pair = SamplingConfig(sampler="dpmpp2m", steps=3)
  assert benchmark.sampled_config(config, pair) is config
  student = benchmark.sampled_config(config, SamplingConfig(sampler="distilled", steps=2))
  assert student.diffusion.guidance_input and not config.diffusion.guidance_input
  assert student.model.cond_dim == config.model.cond_dim + 1
  assert (student.sampling.sampler, student.sampling.steps) == ("distilled", 2)
