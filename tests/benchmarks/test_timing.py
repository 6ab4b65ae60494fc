"""benchmarks.timing: the first call apart from the median, a training step of the demo's
conditioning."""

from configs import diffusion as diffusion_config
from cvmdx_jax import ego_motion
from cvmdx_jax.benchmarks import timing
from cvmdx_jax.config.runs import DiffusionRunConfig


def test_train_timing_feeds_the_conditioning_and_labels_of_the_demo_denoiser():
  base = diffusion_config.get_config("tiny")  # with the demo's conditioning
  base.diffusion.conditioning, base.diffusion.intent_conditioning = "ego_film_residual", True
  config = DiffusionRunConfig.from_config(base).with_tokens(4)
  assert config.model.cond_dim > ego_motion.NUM_FEATURES and config.model.num_intents == 3
  assert timing.train_timing(config, batch=4, repeats=1) > 0


def test_time_calls_reports_the_first_call_apart_from_the_median(monkeypatch):
  clock = {"now": 0.0}
  durations = iter([9.0, 1.0, 3.0, 2.0])  # a compiling first call, then warm calls

  def call():
    clock["now"] += next(durations)

  monkeypatch.setattr(timing.time, "perf_counter", lambda: clock["now"])
  assert timing.time_calls(call, repeats=3, warmup=1) == (9.0, 2.0)
  durations = iter([4.0, 1.0])
  assert timing.time_calls(call, repeats=2, warmup=0) == (4.0, 2.5)  # first also timed
