"""experiments/benchmark.py: its timing lines and the performance options of a run."""

from cvmdx_jax.models.performance import PerformanceOptions
from experiments import benchmark


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
