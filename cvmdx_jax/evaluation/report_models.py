"""The trained runs of a report, loaded and checked once for all its splits."""

import dataclasses
from pathlib import Path

import jax
import numpy as np

from cvmdx_jax.evaluation import learned_baseline, prob_calibration
from cvmdx_jax.inference import mdn_baseline
from cvmdx_jax.inference.bundles import load_baseline, load_denoiser
from cvmdx_jax.inference.predictor import IncompatibleRunsError, Predictor
from cvmdx_jax.runs import layout
from cvmdx_jax.storage import checkpointing, identity


@dataclasses.dataclass(frozen=True)
class Models:
  """What a report evaluates, loaded once for all its splits.

  Attributes:
    predictor: cVMDx (`Predictor`, with the sampling overrides applied).
    ddpm: the `Predictor` of the single-DDPM row (it shares the tokeniser bundle), or None.
    baseline: the WTA MLP (`LearnedBaseline`) or None; mdn: the MDN or None.
    usage: (Q,) training scenarios per token (from the tokeniser's train tokens).
    dirs: {role: run directory} for the report's `_meta`.
    checkpoints: {role: `restored` record} of every loaded run (`_meta.checkpoints`).
  """

  predictor: Predictor
  ddpm: Predictor | None
  baseline: object
  mdn: object
  usage: np.ndarray
  dirs: dict
  checkpoints: dict = dataclasses.field(default_factory=dict)


def restored(run_dir, params) -> dict:
  """{"dir", "checkpoint", "params_id"} of a run loaded from `run_dir`: the step (epoch)
  of its latest complete checkpoint, which the loaders restore, and the content id
  (`identity.content_id`) of the restored parameters `params`."""
  root = Path(run_dir) / layout.CHECKPOINTS
  return {
      "dir": str(run_dir),
      "checkpoint": checkpointing.Checkpoints(root, writable=False).latest_epoch,
      "params_id": identity.content_id(jax.tree.map(np.asarray, params)),
  }


def load(
    *,
    tokenizer_dir,
    diffusion_dir,
    sampling_overrides=None,
    baseline_dir=None,
    ddpm_diffusion_dir=None,
    mdn_dir=None,
) -> Models:
  """Loads and checks the runs of a report (arguments as in `run`); the tokeniser is
  restored once. Raises what `Predictor.load` and `learned_baseline.check_tokenizer` raise."""
  predictor = Predictor.load(tokenizer_dir, diffusion_dir)
  overrides = dict(sampling_overrides or {})
  temperature = overrides.pop("prob_temperature", None)
  if overrides:
    predictor = dataclasses.replace(
        predictor, sampling=dataclasses.replace(predictor.sampling, **overrides)
    )
  if temperature is not None:
    predictor = prob_calibration.with_temperature(predictor, temperature)
  baseline = None if baseline_dir is None else load_baseline(baseline_dir)
  mdn = None if mdn_dir is None else mdn_baseline.load_mdn(mdn_dir)
  for model, where in ((baseline, baseline_dir), (mdn, mdn_dir)):
    if model is not None:
      learned_baseline.check_tokenizer(model, predictor.tokenizer, str(where))
  ddpm = predictor
  if ddpm_diffusion_dir is not None:
    denoiser = load_denoiser(ddpm_diffusion_dir)
    identity.check(
        denoiser.fingerprint.to_dict()["tokenizer"],
        predictor.tokenizer.checkpoint.to_dict(),
        f"denoiser {ddpm_diffusion_dir} (not trained on tokens of tokeniser " f"{tokenizer_dir})",
        IncompatibleRunsError,
    )
    ddpm = Predictor(
        tokenizer=predictor.tokenizer,
        denoiser=denoiser,
        sampling=denoiser.config.sampling,
        delta_limit=predictor.delta_limit,
    )
  if ddpm.denoiser.progressive:
    ddpm = None
  q_count = predictor.tokenizer.config.quantizer.codebook_size
  dirs = {
      "tokenizer_dir": str(tokenizer_dir),
      "diffusion_dir": str(diffusion_dir),
      "ddpm_diffusion_dir": None if ddpm_diffusion_dir is None else str(ddpm_diffusion_dir),
      "baseline_dir": None if baseline_dir is None else str(baseline_dir),
      "mdn_dir": None if mdn_dir is None else str(mdn_dir),
  }
  loaded = {
      "tokenizer": (tokenizer_dir, predictor.tokenizer),
      "diffusion": (diffusion_dir, predictor.denoiser),
      "ddpm_diffusion": (ddpm_diffusion_dir, ddpm and ddpm.denoiser),
      "baseline": (baseline_dir, baseline),
      "mdn": (mdn_dir, mdn),
  }
  checkpoints = {
      role: restored(run_dir, model.params)
      for role, (run_dir, model) in loaded.items()
      if run_dir is not None and model is not None
  }
  usage = np.bincount(predictor.train_tokens.q, minlength=q_count)  # read by Predictor.load
  return Models(predictor, ddpm, baseline, mdn, usage, dirs, checkpoints)


def sampling_meta(predictor: Predictor) -> dict:
  """The sampling settings of a report with the denoiser's control scale, conditioning and
  residual base among them (where metrics.json has always listed them)."""
  targets = predictor.denoiser.config.diffusion
  out = {}
  for name, value in dataclasses.asdict(predictor.sampling).items():
    out[name] = value
    if name == "clip_x0":
      out.update(
          control_scale=targets.control_scale,
          conditioning=targets.conditioning,
          residual_decay_s=targets.residual_decay_s,
      )
  return out
