"""End-to-end speed of cVMDx on this machine, side by side in one run.

  PYTHONPATH=. .venv/bin/python experiments/benchmark.py [--reference_batch=256]

Prints, for the CPU default U-Net (configs/diffusion.py:demo) and the reference-size
U-Net (configs/diffusion.py:paper): the full jitted predict path (9 samples, DDIM 10,
uncertainty-aware CFG, VMM, GMM/BIC hypotheses) at 1 and B scenarios per call
(latency, ms per scenario, scenarios/s, achieved GFLOP/s from XLA's count of one
U-Net forward), DDPM(1000) vs DDIM(10) for one scenario, and training steps/s at
batch 256. Weights are random: speed does not depend on them.
"""

import dataclasses
import time

from absl import flags
import jax
import jax.numpy as jnp

from configs import diffusion as diffusion_config
from cvmdx_jax import diffusion, ego_motion, inference, runs
from cvmdx_jax.models import unet1d
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax import cli

_DEMO_BATCH = flags.DEFINE_integer("demo_batch", 256, "Scenarios per call, CPU default model.")
_REF_BATCH = flags.DEFINE_integer("reference_batch", 16,
                                  "Scenarios per call, reference model (256 takes minutes).")
_TRAIN_BATCH = flags.DEFINE_integer("train_batch", 256, "Batch of the training-step timing.")
_REPEATS = flags.DEFINE_integer("repeats", 2, "Timed calls after the warm-up call.")
NUM_TOKENS = 60
_predict_batch = jax.jit(inference.predict_batch, static_argnames=inference.STATIC_ARGNAMES)


def _time(fn, repeats):
  jax.block_until_ready(fn())
  start = time.perf_counter()
  for _ in range(repeats):
    jax.block_until_ready(fn())
  return (time.perf_counter() - start) / repeats


def forward_flops(graphdef, params, cond_dim: int, batch: int = 1) -> float:
  """XLA's FLOP count of one U-Net forward pass for `batch` sequences."""
  f = jax.jit(lambda p, x, t, q, c: unet1d.apply_unet(graphdef, p, x, t, q, cond=c))
  args = (params, jnp.zeros((batch, 125, 2)), jnp.zeros(batch, jnp.int32),
          jnp.zeros(batch, jnp.int32), jnp.zeros((batch, cond_dim)) if cond_dim else None)
  cost = f.lower(*args).compile().cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else cost
  return float(cost["flops"])


def predict_timing(graphdef, params, b: int, config: inference.SamplingConfig, repeats: int):
  keys = jax.random.split(jax.random.key(0), b)
  schedule = diffusion.cosine_schedule()
  call = lambda: _predict_batch(
      graphdef, params, jnp.arange(b) % NUM_TOKENS, jnp.full(b, 5.0), jnp.full(b, 30.0),
      jnp.zeros(b), keys, jnp.zeros((b, ego_motion.NUM_FEATURES)), schedule=schedule,
      null_token=NUM_TOKENS, config=config)
  return _time(call, repeats)


def train_timing(config, cfg, batch: int, repeats: int):
  _, init_fn, step_fn = diffusion_train.init_and_step(config, cfg, 10_000)
  state = init_fn(jax.random.key(0))
  step = jax.jit(step_fn, donate_argnums=0)
  data = {"x0": jax.random.uniform(jax.random.key(1), (batch, 125, 2), minval=-1, maxval=1),
          "q": jnp.arange(batch) % NUM_TOKENS, "weight": jnp.ones(batch),
          "ego": jnp.zeros((batch, ego_motion.NUM_FEATURES))}
  holder = {"state": state}

  def one():
    holder["state"], metrics = step(holder["state"], data, jax.random.key(2))
    return metrics["loss"]
  return _time(one, repeats)


def main(argv):
  del argv
  print(f"devices: {jax.devices()}")
  for name, preset, big in (("CPU default (:demo)", "demo", _DEMO_BATCH.value),
                            ("reference size (:paper)", "paper", _REF_BATCH.value)):
    config = diffusion_config.get_config(preset)
    cfg = runs.unet_config(config, NUM_TOKENS)
    ddim = inference.SamplingConfig(conditioning=runs.conditioning(config))
    graphdef, params = unet1d.init_unet(cfg, jax.random.key(0))
    gflop = forward_flops(graphdef, params, cfg.cond_dim) / 1e9
    per_scenario = gflop * ddim.num_samples * ddim.steps * 2  # cond + uncond per step
    print(f"\n== {name}: {unet1d.count_params(params) / 1e6:.2f} M parameters, "
          f"{gflop:.3f} GFLOP per sample forward, {per_scenario:.1f} GFLOP per scenario "
          f"(9 samples x 10 steps x 2 for CFG)")
    for b in (1, big):
      sec = predict_timing(graphdef, params, b, ddim, _REPEATS.value)
      print(f"predict  B={b:4d}: {sec:8.3f} s/call  {1000 * sec / b:8.1f} ms/scenario  "
            f"{b / sec:7.1f} scenarios/s  {per_scenario * b / sec:6.1f} GFLOP/s")
    ddpm = dataclasses.replace(ddim, sampler="ddpm")
    t_ddim = predict_timing(graphdef, params, 1, ddim, 1)
    t_ddpm = predict_timing(graphdef, params, 1, ddpm, 1)
    print(f"DDPM(1000) {t_ddpm:.2f} s vs DDIM(10) {t_ddim:.3f} s per scenario (9 samples): "
          f"{t_ddpm / t_ddim:.1f}x")
    sec = train_timing(config, cfg, _TRAIN_BATCH.value, _REPEATS.value)
    print(f"train    B={_TRAIN_BATCH.value}: {sec:.3f} s/step  {1 / sec:.2f} steps/s")


for _name in ("demo_batch", "reference_batch", "train_batch", "repeats"):
  flags.register_validator(_name, lambda v: v >= 1, "must be >= 1")

if __name__ == "__main__":
  cli.run(main)
