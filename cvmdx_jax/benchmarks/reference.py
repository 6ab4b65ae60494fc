"""The official-size timings in ../shared/reference_bench's schema and their tables:
`reference_timings` (seconds per prediction call at B = 1 and B = big, per training step),
`read_timings` (a timing JSON, checked), the official / ours ratios and the table of the
performance options."""

import json
from pathlib import Path

from cvmdx_jax.benchmarks import random_models
from cvmdx_jax.benchmarks.timing import predict_calls, train_timing
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.errors import UserError
from cvmdx_jax.models import unet1d
from cvmdx_jax.models.performance import PerformanceOptions
from cvmdx_jax.train import distill

REFERENCE_TOKENS = 256  # the official model: num_classes = 257 = Q + the null token
# (warm-up calls, timed calls) of the reference timings: b1, big, train
REFERENCE_REPEATS = {"b1": (1, 7), "big": (1, 3), "train": (2, 5)}


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
  denoiser = random_models.random_denoiser(sampled)
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
