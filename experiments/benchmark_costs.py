"""Cost curves on this machine: prediction time and memory against the samples N and the
scenarios M, training time per epoch against the train scenarios, with log-log slopes.

  .venv/bin/python experiments/benchmark_costs.py --workdir=runs/benchmark_costs \
      [--samples=9,32,128] [--scenarios=1,10,100,1000] [--train_sizes=256,512,1024]

The models are the demo's (configs/tokenizer.py:demo, the U-Net of configs/diffusion.py:demo
sampled by the default sampler: the distilled student, 2 steps, k-means hypotheses) with
random weights (time and memory do not depend on them), behind the `Predictor` (chunks of
--chunk scenarios, one jitted call each). Each point is the median of --timed_calls calls
after a warm-up call that compiles its shape; its memory is the most resident memory
above the start of one warm call (`memory.call_peak`, after the host allocator returned
its freed pages; the script keeps the system allocator, so freed buffers leave). The epoch
is the demo's: shuffled batches of --epoch_batch gathered on the host, one jitted AdamW
step each (the last batch padded). Writes <workdir>/costs.json and three log-log PNGs
(predict_vs_samples.png, predict_vs_scenarios.png, train_epoch_vs_scenarios.png) and
prints each curve's fitted slope (1 = linear), over all points and over the upper half.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import io
import statistics
import time
from pathlib import Path

import jax
import matplotlib
import numpy as np
from absl import app, flags

from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax import constants
from cvmdx_jax.benchmarks import random_models
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig, TokenizerRunConfig
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.runs import memory
from cvmdx_jax.storage import atomic
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import distill

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402  (after the backend is chosen)

_WORKDIR = flags.DEFINE_string("workdir", "runs/benchmark_costs", "Where the curves go.")
_SAMPLES = flags.DEFINE_list("samples", ["9", "32", "128"], "N of the samples curve.")
_SAMPLES_M = flags.DEFINE_integer(
    "samples_scenarios", 8, "Scenarios per call of the samples " "curve.", lower_bound=1
)
_SCENARIOS = flags.DEFINE_list(
    "scenarios",
    ["1", "10", "100", "1000"],
    "M of the scenarios curve (10000 takes minutes on 2 cores).",
)
_SCENARIOS_N = flags.DEFINE_integer(
    "scenarios_samples",
    9,
    "N of the scenarios curve (the " "paper's; the demo draws 64).",
    lower_bound=1,
)
_CHUNK = flags.DEFINE_integer(
    "chunk", 64, "Predictor chunk: scenarios per jitted call.", lower_bound=1
)
_TRAIN_SIZES = flags.DEFINE_list(
    "train_sizes", ["256", "512", "1024"], "Train scenarios of the epoch curve."
)
_TRAIN_BATCH = flags.DEFINE_integer(
    "epoch_batch", 128, "Batch of the epoch (the demo's).", lower_bound=1
)
_REPEATS = flags.DEFINE_integer("timed_calls", 2, "Timed calls per point.", lower_bound=1)
cli.output_dirs("workdir")
for _name in ("samples", "scenarios", "train_sizes"):
  cli.int_list(_name, 1)


def demo_predictor(num_samples: int, chunk: int) -> Predictor:
  """A `Predictor` of the demo's tokeniser and distilled U-Net, random weights, drawing
  `num_samples` samples per scenario, `chunk` scenarios per call."""
  tok_cfg = TokenizerRunConfig.from_config(tokenizer_config.get_config("demo")).model
  config = student_run_config(tok_cfg.quantizer.codebook_size)
  sampling = dataclasses.replace(config.sampling, num_samples=num_samples)
  return random_models.random_predictor(tok_cfg, config, sampling, chunk)


def student_run_config(num_tokens: int) -> DiffusionRunConfig:
  """configs/diffusion.py:demo for `num_tokens` tokens as its 2-step distilled student."""
  teacher = DiffusionRunConfig.from_config(diffusion_config.get_config("demo"))
  return distill.student_config(teacher.with_tokens(num_tokens), DistillRunConfig(steps=2))


def timed_point(fn, warmup_fn, repeats: int) -> dict:
  """{"seconds": median of `repeats` calls of fn, "peak_mib": the resident memory one warm
  call of fn adds at its peak}; `warmup_fn` first (it compiles the shapes fn needs)."""
  warmup_fn()
  memory.release_freed()
  _, peak = memory.call_peak(fn)
  times = []
  for _ in range(repeats):
    start = time.perf_counter()
    fn()
    times.append(time.perf_counter() - start)
  return {"seconds": statistics.median(times), "peak_mib": peak / 2**20}


def samples_curve(sizes, m: int, chunk: int, repeats: int) -> list[dict]:
  """Prediction of `m` scenarios (one call) against N."""
  scenarios, rows = random_models.random_scenarios(m), []
  for n in sizes:
    predictor = demo_predictor(n, chunk)
    call = lambda: predictor(scenarios)
    rows.append({"x": n, **timed_point(call, call, repeats)})
    print(f"N = {n:4d}, M = {m}: {rows[-1]}", flush=True)
  return rows


def scenarios_curve(sizes, n: int, chunk: int, repeats: int) -> list[dict]:
  """Prediction of M scenarios (chunks of `chunk`) against M."""
  predictor, rows = demo_predictor(n, chunk), []
  for m in sizes:
    scenarios = random_models.random_scenarios(m)
    first = scenarios.take(np.arange(min(m, chunk)))  # the chunk's shape, compiled
    point = timed_point(
        lambda: predictor(scenarios), lambda: predictor(first), repeats if m <= chunk else 1
    )
    rows.append({"x": m, **point})
    print(f"M = {m:5d}, N = {n}: {rows[-1]}", flush=True)
  return rows


def epoch_curve(sizes, batch: int, repeats: int) -> list[dict]:
  """Seconds of one training epoch of the demo denoiser against the train scenarios."""
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("demo")).with_tokens(64)
  model = config.model
  _, init_fn, step_fn = diffusion_train.init_and_step(config, 10_000)
  step = jax.jit(step_fn, donate_argnums=0)
  holder = {"state": init_fn(jax.random.key(0))}
  rows = []
  for size in sizes:
    rng = np.random.default_rng(size)
    data = {
        "x0": rng.uniform(-1, 1, (size, constants.T_PRED, 2)).astype(np.float32),
        "q": (np.arange(size) % model.null_token).astype(np.int32),
        "weight": np.ones(size, np.float32),
        "ego": np.zeros((size, model.cond_dim), np.float32),
    }
    if model.num_intents:
      data["label"] = (np.arange(size) % model.num_intents).astype(np.int32)

    def epoch(data=data, size=size):
      order = rng.permutation(size)
      for start in range(0, size, batch):
        idx = np.resize(order[start : start + batch], batch)  # the last batch padded
        holder["state"], metrics = step(
            holder["state"], {k: v[idx] for k, v in data.items()}, jax.random.key(start)
        )
      return jax.block_until_ready(metrics["loss"])

    rows.append({"x": size, **timed_point(epoch, epoch, repeats)})
    print(f"train scenarios = {size:5d}, batch {batch}: {rows[-1]}", flush=True)
  return rows


def slopes(rows: list[dict], key: str) -> tuple[float, float]:
  """Least-squares slopes of log(key) on log(x): over all rows, over the upper half of x."""
  x = np.log([r["x"] for r in rows])
  y = np.log([max(r[key], 1e-9) for r in rows])
  upper = slice(len(rows) // 2, None) if len(rows) > 3 else slice(None)
  fit = lambda a, b: float(np.polyfit(a, b, 1)[0]) if len(a) > 1 else float("nan")
  return fit(x, y), fit(x[upper], y[upper])


def plot(rows: list[dict], xlabel: str, title: str, memory_too: bool) -> bytes:
  """A log-log PNG of seconds (and peak MiB, on a second axis) against x."""
  fig, ax = plt.subplots(figsize=(4.2, 3.0), dpi=90)
  x = [r["x"] for r in rows]
  ax.loglog(x, [r["seconds"] for r in rows], "o-", color="C0", label="time")
  ax.set_xlabel(xlabel)
  ax.set_ylabel("seconds", color="C0")
  if memory_too:
    mem = ax.twinx()
    mem.loglog(x, [max(r["peak_mib"], 1.0) for r in rows], "s--", color="C1")
    mem.set_ylabel("peak resident memory added (MiB)", color="C1")
  ax.set_title(title, fontsize=9)
  fig.tight_layout()
  buffer = io.BytesIO()
  fig.savefig(buffer, format="png")
  plt.close(fig)
  return buffer.getvalue()


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  out = Path(_WORKDIR.value)
  ints = lambda flag: [int(v) for v in flag.value]
  chunk, repeats = _CHUNK.value, _REPEATS.value
  curves = {
      "predict_vs_samples": (
          samples_curve(ints(_SAMPLES), _SAMPLES_M.value, chunk, repeats),
          "samples N per scenario",
          f"predict {_SAMPLES_M.value} scenarios",
      ),
      "predict_vs_scenarios": (
          scenarios_curve(ints(_SCENARIOS), _SCENARIOS_N.value, chunk, repeats),
          "scenarios M",
          f"predict, N = {_SCENARIOS_N.value}, chunks of {chunk}",
      ),
      "train_epoch_vs_scenarios": (
          epoch_curve(ints(_TRAIN_SIZES), _TRAIN_BATCH.value, repeats),
          "train scenarios",
          f"one epoch, batch {_TRAIN_BATCH.value}",
      ),
  }
  files, summary = {}, {"backend": jax.default_backend(), "devices": len(jax.devices())}
  for name, (rows, xlabel, title) in curves.items():
    fits = {key: slopes(rows, key) for key in ("seconds", "peak_mib")}
    summary[name] = {"rows": rows, "slopes": fits}
    files[out / f"{name}.png"] = plot(rows, xlabel, title, name.startswith("predict"))
    for key, (whole, upper) in fits.items():
      print(
          f"{name}: log-log slope of {key}: {whole:.2f} (all points), {upper:.2f} " "(upper half)",
          flush=True,
      )
  files[out / "costs.json"] = atomic.json_text(summary, indent=1).encode()
  out.mkdir(parents=True, exist_ok=True)
  atomic.write_all(files)
  print(f"wrote {', '.join(str(p) for p in files)}", flush=True)


if __name__ == "__main__":
  cli.run(main)
