"""Timing of jitted calls for experiments/benchmark*.py: the first call and the median of
warm ones, one prediction of a denoiser, one training step, XLA's FLOP count of a U-Net
forward. Weights are random where these build models: speed does not depend on them."""

import dataclasses
import statistics
import time

import jax
import jax.numpy as jnp

from cvmdx_jax import diffusion, ego_motion
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.inference import sampling as sampling_lib
from cvmdx_jax.inference.bundles import Denoiser
from cvmdx_jax.models import unet1d
from cvmdx_jax.train import diffusion as diffusion_train

_predict_batch = jax.jit(sampling_lib.predict_batch, static_argnames=sampling_lib.STATIC_ARGNAMES)


def time_calls(fn, repeats: int, warmup: int = 1) -> tuple[float, float]:
  """(seconds of the first call, median seconds of the `repeats` calls after `warmup`
  calls) of `fn`; the first call is the first warm-up call where there is one (for a
  function not called before: trace, compile and run)."""
  times = []
  for _ in range(warmup + repeats):
    start = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - start)
  return times[0], statistics.median(times[warmup:])


def forward_flops(graphdef, params, cond_dim: int, batch: int = 1) -> float:
  """XLA's FLOP count of one U-Net forward pass for `batch` sequences, of the lowered
  computation: after compiling for a GPU the count leaves out the convolutions handed to
  cuDNN (0.004 against 0.045 GFLOP for the demo U-Net on an H200)."""
  f = jax.jit(lambda p, x, t, q, c: unet1d.apply_unet(graphdef, p, x, t, q, cond=c))
  args = (
      params,
      jnp.zeros((batch, 125, 2)),
      jnp.zeros(batch, jnp.int32),
      jnp.zeros(batch, jnp.int32),
      jnp.zeros((batch, cond_dim)) if cond_dim else None,
  )
  cost = f.lower(*args).cost_analysis()
  cost = cost[0] if isinstance(cost, (list, tuple)) else cost
  return float(cost["flops"])


def predict_calls(
    denoiser: Denoiser, b: int, config: SamplingConfig, repeats: int, warmup: int = 1
) -> tuple[float, float]:
  """`time_calls` of one jitted `predict_batch` call of `denoiser` for `b` scenarios:
  (first, median) s; its parameters prepared for inference first, untimed, as `Predictor`
  does on construction (`unet1d.prepare_params`)."""
  denoiser = dataclasses.replace(
      denoiser, params=unet1d.prepare_params(denoiser.graphdef, denoiser.params)
  )
  keys = jax.random.split(jax.random.key(0), b)
  schedule = diffusion.cosine_schedule()
  call = lambda: _predict_batch(
      denoiser,
      jnp.arange(b) % denoiser.null_token,
      jnp.full(b, 5.0),
      jnp.full(b, 30.0),
      jnp.zeros(b),
      keys,
      jnp.zeros((b, ego_motion.NUM_FEATURES)),
      schedule=schedule,
      config=config,
  )
  return time_calls(call, repeats, warmup)


def train_timing(config: DiffusionRunConfig, batch: int, repeats: int, warmup: int = 1):
  """Median seconds of one jitted training step (AdamW, EMA) at `batch` (`config.model`
  sized for its tokens; the conditioning vector and intent labels its config asks for)."""
  _, init_fn, step_fn = diffusion_train.init_and_step(config, 10_000)
  state = init_fn(jax.random.key(0))
  step = jax.jit(step_fn, donate_argnums=0)
  model = config.model
  data = {
      "x0": jax.random.uniform(jax.random.key(1), (batch, 125, 2), minval=-1, maxval=1),
      "q": jnp.arange(batch) % model.null_token,
      "weight": jnp.ones(batch),
      "ego": jnp.zeros((batch, model.cond_dim)),
  }
  if model.num_intents:
    data["label"] = jnp.arange(batch) % model.num_intents
  holder = {"state": state}

  def one():
    holder["state"], metrics = step(holder["state"], data, jax.random.key(2))
    return metrics["loss"]

  return time_calls(one, repeats, warmup)[1]
