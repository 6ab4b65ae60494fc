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

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import os

import jax
from absl import flags

from configs import diffusion as diffusion_config
from configs import distill as distill_config
from cvmdx_jax import host_allocator
from cvmdx_jax.benchmarks import random_models, reference
from cvmdx_jax.benchmarks.timing import forward_flops, predict_calls, train_timing
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.models import performance, unet1d
from cvmdx_jax.models.performance import PerformanceOptions
from cvmdx_jax.storage import atomic

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
# --performance=all: each combination of the options
OPTION_COMBINATIONS = tuple(
    PerformanceOptions(winograd, norm) for winograd in ("on", "off") for norm in ("on", "off")
)


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


def run_options(choice: str | None, in_force: PerformanceOptions) -> PerformanceOptions:
  """The performance options of a run: `in_force` (the environment's) without a
  --performance choice or with "all" (which sets each combination itself), else `choice`
  for every option."""
  if choice in (None, "all"):
    return in_force
  return PerformanceOptions(**dict.fromkeys(dataclasses.asdict(in_force), choice))


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
              reference.reference_timings(
                  config,
                  reference.REFERENCE_TOKENS,
                  sampling,
                  big=_BIG.value,
                  train_batch=_TRAIN_BATCH.value,
              ),
          )
      )
    print(f"timed {options}", flush=True)
  print(
      f"\nofficial size, {sampling.sampler} {sampling.steps} steps, on "
      f"{jax.default_backend()}:\n{reference.performance_table(rows, jax.default_backend())}"
  )


def reference_main():
  """--reference_json / --official_json: the official-size timings and the ratio table."""
  official = reference.read_timings(_OFFICIAL_JSON.value) if _OFFICIAL_JSON.value else None
  config, sampling = _reference_setup()
  ours = reference.reference_timings(config, reference.REFERENCE_TOKENS, sampling, big=_BIG.value)
  print(
      f"reference size: {ours['params'] / 1e6:.2f} M parameters, {sampling.sampler} "
      f"{sampling.steps} steps: B=1 {ours['b1']['total']:.3f} s (first call "
      f"{ours['b1']['first']:.2f} s), B={ours['big']['b']} {ours['big']['total']:.3f} s, "
      f"train {ours['train']['step']:.3f} s/step"
  )
  if _REFERENCE_JSON.value:
    atomic.write_json(_REFERENCE_JSON.value, ours, indent=1)
  if official is not None:
    print(reference.ratio_table(official, ours))


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
    teacher = random_models.random_denoiser(config)
    gflop = forward_flops(teacher.graphdef, teacher.params, cfg.cond_dim) / 1e9
    per_scenario = gflop * ddim.num_samples * ddim.steps * 2  # cond + uncond per step
    print(
        f"\n== {name}: {unet1d.count_params(teacher.params) / 1e6:.2f} M parameters, "
        f"{gflop:.3f} GFLOP per sample forward, {per_scenario:.1f} GFLOP per scenario "
        f"(9 samples x 10 steps x 2 for CFG)"
    )
    student = reference.sampled_config(config, fast)
    fast_net = teacher if student is config else random_models.random_denoiser(student)
    for sampling, label, gflop, denoiser in (
        (ddim, "", per_scenario, teacher),
        (fast, f" {fast.sampler}({fast.steps})", None, fast_net),
    ):
      first, sec = predict_calls(denoiser, 1, sampling, _REPEATS.value)
      print(predict_line(label, 1, sec, gflop, first))
      sec = predict_calls(denoiser, big, sampling, _REPEATS.value)[1]
      print(predict_line(label, big, sec, gflop))
    ddpm = dataclasses.replace(ddim, sampler="ddpm")
    t_ddim, t_ddpm = (predict_calls(teacher, 1, s, 1)[1] for s in (ddim, ddpm))
    t_fast = predict_calls(fast_net, 1, fast, 1)[1]
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
