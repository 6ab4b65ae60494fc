"""End-to-end speed of cVMDx on this machine, side by side in one run.

  .venv/bin/python experiments/benchmark.py [--reference_batch=256] [--performance=off]

Prints the backend, its devices, the performance options in force (`models.performance`,
`--performance`) and the host allocator, then, for the CPU default U-Net
(configs/diffusion.py:demo) and the reference-size U-Net (configs/diffusion.py:paper): the
full jitted predict path (9 samples, DDIM 10, uncertainty-aware CFG, VMM, GMM/BIC
hypotheses) at 1 and B scenarios per call (latency, ms per scenario, scenarios/s, achieved
GFLOP/s from XLA's count of one U-Net forward), the same with the default sampler
(configs/diffusion.py, no preset), DDPM(1000) against DDIM(10) and against the default
sampler for one scenario, and training steps/s at batch 256. The B = 1 lines also give the
first call (trace + compile + run; a compile can be a read of JAX's persistent cache where
`JAX_COMPILATION_CACHE_DIR` is set) apart from the median of the warm calls. Weights are
random: speed does not depend on them. Runs unchanged on any backend.

  .venv/bin/python experiments/benchmark.py --performance=all

times instead the official-size prediction and training step below with each combination
of the options `winograd` and `group_norm_backward` on and off, as a table (the measurement
behind "auto" on a backend).

Against the official code (../shared/reference_bench, run its official_timing.py first):

  .venv/bin/python experiments/benchmark.py \
      --reference_json=/tmp/ours.json --official_json=/tmp/official.json

times only the official-size U-Net (configs/diffusion.py:reference with Q = 256 tokens:
22.47 M parameters) with the default sampling settings and writes
{"params", "b1": {"total"}, "big": {"total", "b"}, "train": {"step", "batch"}}: seconds
per call for 1 and for 32 (--big) scenarios end to end (sampling, VMM, hypotheses; the official
"total" is DDIM + post-processing per call), and per AdamW step at batch 256; medians
of repeated calls after a warm-up. Ours also holds "b1": {"first"}, the first call (trace +
compile + run), which the official JSON does not have. With --official_json it prints
official / ours.
"""

import dataclasses
import json
import os
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
from absl import flags

from configs import diffusion as diffusion_config
from configs import distill as distill_config
from cvmdx_jax import cli, diffusion, ego_motion, host_allocator
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference import sampling as sampling_lib
from cvmdx_jax.inference.bundles import Denoiser
from cvmdx_jax.models import performance, unet1d
from cvmdx_jax.models.performance import PerformanceOptions
from cvmdx_jax.storage import atomic
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import distill

_DEMO_BATCH = flags.DEFINE_integer("demo_batch", 256, "Scenarios per call, CPU default model.")
_REF_BATCH = flags.DEFINE_integer(
    "reference_batch", 16, "Scenarios per call, reference model (256 takes minutes)."
)
_TRAIN_BATCH = flags.DEFINE_integer("train_batch", 256, "Batch of the training-step timing.")
_REPEATS = flags.DEFINE_integer("repeats", 2, "Timed calls after the warm-up call.")
_REFERENCE_JSON = flags.DEFINE_string(
    "reference_json",
    None,
    "Time only the official-size U-Net and write its timings here "
    "(the ../shared/reference_bench schema).",
)
_OFFICIAL_JSON = flags.DEFINE_string(
    "official_json",
    None,
    "official_timing.py output: print official / ours (implies the " "reference-size timing).",
)
_BIG = flags.DEFINE_integer(
    "big", 32, "Scenarios per call of the reference 'big' timing " "(official_timing.py: BIG, 32)."
)
_SAMPLER = flags.DEFINE_string(
    "sampler",
    None,
    "Sampler timed as the default " "(default: configs/diffusion.py without a preset).",
)
_STEPS = flags.DEFINE_integer("steps", None, "Steps of --sampler (default: the config's).")
_PERFORMANCE = flags.DEFINE_enum(
    "performance",
    None,
    ["auto", "on", "off", "all"],
    "Performance options "
    "(cvmdx_jax/models/performance.py) of the run: auto, on or off for all of them (default: "
    "as CVMDX_WINOGRAD, CVMDX_GROUP_NORM_BACKWARD set them); all: instead, the official-size "
    "timings with each combination of on and off, as a table.",
)
NUM_TOKENS = 60
REFERENCE_TOKENS = 256  # the official model: num_classes = 257 = Q + the null token
# (warm-up calls, timed calls) of the reference timings: b1, big, train
REFERENCE_REPEATS = {"b1": (1, 7), "big": (1, 3), "train": (2, 5)}
# --performance=all: each combination of the options
OPTION_COMBINATIONS = tuple(
    PerformanceOptions(winograd, norm) for winograd in ("on", "off") for norm in ("on", "off")
)
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


def _time(fn, repeats, warmup=1):
  """Median seconds of `repeats` calls of `fn` after `warmup` untimed calls."""
  return time_calls(fn, repeats, warmup)[1]


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


def bundle(config: DiffusionRunConfig, key=None) -> Denoiser:
  """A `Denoiser` of `config` (sized for its tokens) with fresh parameters of `key`."""
  graphdef, params = unet1d.init_unet(config.model, jax.random.key(0) if key is None else key)
  return Denoiser(params, graphdef, config, ml_collections.FrozenConfigDict({}))


def predict_timing(*args, **kwargs) -> float:
  """Median seconds of one jitted `predict_batch` call for `b` scenarios (`predict_calls`)."""
  return predict_calls(*args, **kwargs)[1]


def predict_line(
    label: str, b: int, seconds: float, gflop: float | None = None, first: float | None = None
) -> str:
  """One line of prediction timings: `seconds` per call of `b` scenarios; achieved GFLOP/s
  from `gflop` per scenario; the `first` call's seconds beside them."""
  line = (
      f"predict  B={b:4d}{label}: {seconds:8.3f} s/call  {1000 * seconds / b:8.1f} "
      f"ms/scenario  {b / seconds:7.1f} scenarios/s"
  )
  if gflop:
    line += f"  {gflop * b / seconds:6.1f} GFLOP/s"
  if first is not None:
    line += f"  (first call {first:.2f} s: trace, compile, run)"
  return line


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

  return _time(one, repeats, warmup)


def default_sampling(base: SamplingConfig) -> SamplingConfig:
  """`base` with the default sampler and steps: --sampler and --steps, else the default
  pipeline's, the last student of `configs.distill.STUDENTS` (sampler "distilled")."""
  sampler = _SAMPLER.value or "distilled"
  default = (
      distill_config.STUDENTS[-1]
      if sampler == "distilled"
      else diffusion_config.get_config().sampling.steps
  )
  return dataclasses.replace(base, sampler=sampler, steps=_STEPS.value or default)


def sampled_config(config: DiffusionRunConfig, sampling: SamplingConfig) -> DiffusionRunConfig:
  """The run `sampling` samples: for the distilled sampler the student of `config` (w as an
  input, `train.distill.student_config`), else `config`."""
  if sampling.sampler != "distilled":
    return config
  return distill.student_config(config, DistillRunConfig(steps=sampling.steps))


def reference_timings(
    config: DiffusionRunConfig,
    num_tokens: int,
    sampling: SamplingConfig,
    *,
    big: int = 32,
    train_batch: int = 256,
    repeats=REFERENCE_REPEATS,
) -> dict:
  """Timings in the ../shared/reference_bench schema, seconds (medians).

  Returns:
    {"params", "sampler", "steps", "b1": {"total", "first"}, "big": {"total", "b"},
     "train": {"step", "batch"}}; "total" is one predict_batch call end to end, "first"
    the first one (trace, compile and run).
  """
  config = config.with_tokens(num_tokens)
  sampled = sampled_config(config, sampling)
  denoiser = bundle(sampled)
  params = denoiser.params
  timed = lambda b, key: predict_calls(denoiser, b, sampling, repeats[key][1], repeats[key][0])
  train_warmup, train_repeats = repeats["train"]
  first, b1 = timed(1, "b1")
  return {
      "params": unet1d.count_params(params),
      "sampler": sampling.sampler,
      "steps": sampling.steps,
      "b1": {"total": b1, "first": first},
      "big": {"total": timed(big, "big")[1], "b": big},
      "train": {
          "step": train_timing(config, train_batch, train_repeats, train_warmup),
          "batch": train_batch,
      },
  }


def read_timings(path) -> dict:
  """A timing JSON in the reference_bench schema.

  Raises:
    ValueError: a field is missing or not a positive number (names the file and field).
  """
  timings = json.loads(Path(path).read_text())
  for group, field in (("b1", "total"), ("big", "total"), ("big", "b"), ("train", "step")):
    value = timings.get(group, {}).get(field) if isinstance(timings.get(group), dict) else None
    if not isinstance(value, (int, float)) or value <= 0:
      raise UserError(f"{path}: field {group}.{field} must be a positive number, got {value!r}")
  return timings


def ratio_rows(official: dict, ours: dict) -> list[tuple[str, float, float, float]]:
  """(what, official s, ours s, official / ours) per scenario at B = 1, per scenario at
  B = big, per training step."""
  per = lambda t: t["big"]["total"] / t["big"]["b"]
  return [
      (what, off, mine, off / mine)
      for what, off, mine in (
          ("1 scenario, end to end", official["b1"]["total"], ours["b1"]["total"]),
          (f"{ours['big']['b']} scenarios, per scenario", per(official), per(ours)),
          (
              f"training step, batch {ours['train']['batch']}",
              official["train"]["step"],
              ours["train"]["step"],
          ),
      )
  ]


def ratio_table(official: dict, ours: dict) -> str:
  """Markdown table of `ratio_rows`."""
  lines = ["| what | official | cvmdx_jax | official / cvmdx_jax |", "|---|---|---|---|"]
  lines += [
      f"| {what} | {off:.3g} s | {mine:.3g} s | {ratio:.2f}x |"
      for what, off, mine, ratio in ratio_rows(official, ours)
  ]
  return "\n".join(lines)


def run_options(choice: str | None, in_force: PerformanceOptions) -> PerformanceOptions:
  """The performance options of a run: `in_force` (the environment's) without a
  --performance choice or with "all" (which sets each combination itself), else `choice`
  for every option."""
  if choice in (None, "all"):
    return in_force
  return PerformanceOptions(**dict.fromkeys(dataclasses.asdict(in_force), choice))


def performance_table(rows: list[tuple[PerformanceOptions, dict]], platform: str) -> str:
  """Markdown table of (options, `reference_timings`) rows; the column "auto" marks the
  row that "auto" takes on `platform`."""
  auto = PerformanceOptions().resolved(platform)
  lines = [
      f"| winograd | group_norm_backward | auto on {platform} | B=1 first call | B=1 | "
      "B=big per scenario | training step |",
      "|---|---|---|---|---|---|---|",
  ]
  for options, t in rows:
    lines.append(
        f"| {options.winograd} | {options.group_norm_backward} | "
        f"{'x' if options.resolved(platform) == auto else ''} | "
        f"{t['b1']['first']:.2f} s | {t['b1']['total']:.3f} s | "
        f"{t['big']['total'] / t['big']['b']:.3f} s (B={t['big']['b']}) | "
        f"{t['train']['step']:.3f} s (batch {t['train']['batch']}) |"
    )
  return "\n".join(lines)


def _reference_setup() -> tuple[DiffusionRunConfig, SamplingConfig]:
  """The official-size config (configs/diffusion.py:reference) and its default sampling."""
  config = DiffusionRunConfig.from_config(diffusion_config.get_config("reference"))
  return config, default_sampling(config.sampling)


def performance_main():
  """--performance=all: the official-size timings with each of `OPTION_COMBINATIONS`."""
  config, sampling = _reference_setup()
  rows = []
  for options in OPTION_COMBINATIONS:
    with performance.use(options):
      rows.append(
          (
              options,
              reference_timings(
                  config, REFERENCE_TOKENS, sampling, big=_BIG.value, train_batch=_TRAIN_BATCH.value
              ),
          )
      )
    print(f"timed {options}", flush=True)
  print(
      f"\nofficial size, {sampling.sampler} {sampling.steps} steps, on "
      f"{jax.default_backend()}:\n{performance_table(rows, jax.default_backend())}"
  )


def reference_main():
  """--reference_json / --official_json: the official-size timings and the ratio table."""
  official = read_timings(_OFFICIAL_JSON.value) if _OFFICIAL_JSON.value else None
  config, sampling = _reference_setup()
  ours = reference_timings(config, REFERENCE_TOKENS, sampling, big=_BIG.value)
  print(
      f"reference size: {ours['params'] / 1e6:.2f} M parameters, {sampling.sampler} "
      f"{sampling.steps} steps: B=1 {ours['b1']['total']:.3f} s (first call "
      f"{ours['b1']['first']:.2f} s), B={ours['big']['b']} {ours['big']['total']:.3f} s, "
      f"train {ours['train']['step']:.3f} s/step"
  )
  if _REFERENCE_JSON.value:
    atomic.write_json(_REFERENCE_JSON.value, ours, indent=1)
  if official is not None:
    print(ratio_table(official, ours))


def main(argv):
  del argv
  options = run_options(_PERFORMANCE.value, performance.current())
  backend = jax.default_backend()
  print(f"backend: {backend}; devices: {jax.devices()}")
  print(
      f"performance options (on/off as taken here): {options.describe(backend)}; "
      f"host allocator: {host_allocator.in_force(os.environ)}"
  )
  with performance.use(options):
    if _PERFORMANCE.value == "all":
      performance_main()
    elif _REFERENCE_JSON.value or _OFFICIAL_JSON.value:
      reference_main()
    else:
      default_main()


def default_main():
  """The timings of the module docstring's first command."""
  for name, preset, big in (
      ("CPU default (:demo)", "demo", _DEMO_BATCH.value),
      ("reference size (:paper)", "paper", _REF_BATCH.value),
  ):
    config = DiffusionRunConfig.from_config(diffusion_config.get_config(preset)).with_tokens(
        NUM_TOKENS
    )
    cfg = config.model
    ddim = SamplingConfig()
    fast = default_sampling(ddim)
    graphdef, params = unet1d.init_unet(cfg, jax.random.key(0))
    gflop = forward_flops(graphdef, params, cfg.cond_dim) / 1e9
    per_scenario = gflop * ddim.num_samples * ddim.steps * 2  # cond + uncond per step
    print(
        f"\n== {name}: {unet1d.count_params(params) / 1e6:.2f} M parameters, "
        f"{gflop:.3f} GFLOP per sample forward, {per_scenario:.1f} GFLOP per scenario "
        f"(9 samples x 10 steps x 2 for CFG)"
    )
    teacher = Denoiser(params, graphdef, config, ml_collections.FrozenConfigDict({}))
    student = sampled_config(config, fast)
    fast_net = teacher if student is config else bundle(student)
    for sampling, label, gflop, denoiser in (
        (ddim, "", per_scenario, teacher),
        (fast, f" {fast.sampler}({fast.steps})", None, fast_net),
    ):
      first, sec = predict_calls(denoiser, 1, sampling, _REPEATS.value)
      print(predict_line(label, 1, sec, gflop, first))
      sec = predict_timing(denoiser, big, sampling, _REPEATS.value)
      print(predict_line(label, big, sec, gflop))
    ddpm = dataclasses.replace(ddim, sampler="ddpm")
    t_ddim, t_ddpm = (predict_timing(teacher, 1, s, 1) for s in (ddim, ddpm))
    t_fast = predict_timing(fast_net, 1, fast, 1)
    print(
        f"DDPM(1000) {t_ddpm:.2f} s vs DDIM(10) {t_ddim:.3f} s per scenario (9 samples): "
        f"{t_ddpm / t_ddim:.1f}x"
    )
    print(
        f"DDPM(1000) {t_ddpm:.2f} s vs default {fast.sampler}({fast.steps}) {t_fast:.3f} s "
        f"per scenario (9 samples): {t_ddpm / t_fast:.1f}x"
    )
    sec = train_timing(config, _TRAIN_BATCH.value, _REPEATS.value)
    print(f"train    B={_TRAIN_BATCH.value}: {sec:.3f} s/step  {1 / sec:.2f} steps/s")


for _name in ("demo_batch", "reference_batch", "train_batch", "repeats"):
  flags.register_validator(_name, lambda v: v >= 1, "must be >= 1")

if __name__ == "__main__":
  cli.run(main, allocator=True)
