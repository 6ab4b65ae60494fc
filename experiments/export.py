"""Exports a trained cVMDx (tokeniser + denoiser or distilled student) as `jax.export`
artefacts that run with JAX alone, without this package.

  .venv/bin/python experiments/export.py --tokenizer_dir=runs/demo/tokenizer \\
      --diffusion_dir=runs/demo/student_progressive_1 --out=runs/demo/export

writes <out>/predict.jax (the whole prediction), <out>/denoiser.jax (one denoiser
evaluation), <out>/manifest.json and <out>/checksums.json (`cvmdx_jax.inference.export`),
with --onnx also <out>/denoiser.onnx;
`--num_samples` / `--sampler` / `--steps` override the run's sampling settings, which are
baked into predict.jax. experiments/run_exported.py loads and runs them with JAX alone.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses

from absl import app, flags

from cvmdx_jax.config import sampling
from cvmdx_jax.inference import export
from cvmdx_jax.inference.predictor import Predictor

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion or distilled run directory.")
_OUT = flags.DEFINE_string("out", None, "Output directory of the artefacts.")
_SAMPLES = flags.DEFINE_integer(
    "num_samples", None, "Samples per scenario instead of the " "run's.", lower_bound=1
)
_SAMPLER = flags.DEFINE_enum(
    "sampler", None, list(sampling.SAMPLERS), "Sampler instead of the run's."
)
_STEPS = flags.DEFINE_integer("steps", None, "Sampling steps instead of the run's.", lower_bound=1)
_NOISE_IDS = flags.DEFINE_integer(
    "num_noise_ids",
    1,
    "K of predict.jax's noise_ids input "
    "(b, K): 1 = the scenario's position (Predictor's default), "
    "2 = (frame, track id) as inference.stream.",
    lower_bound=1,
)
_ONNX = flags.DEFINE_bool(
    "onnx",
    False,
    "Also write denoiser.onnx (needs jax2onnx: pip "
    "install --no-deps -r requirements-onnx.lock).",
)
flags.mark_flags_as_required(["tokenizer_dir", "diffusion_dir", "out"])
cli.input_dirs("tokenizer_dir", "diffusion_dir")
cli.output_dirs("out")


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"Unexpected arguments: {argv[1:]}")
  predictor = Predictor.load(_TOKENIZER.value, _DIFFUSION.value)
  overrides = {
      k: v
      for k, v in (
          ("num_samples", _SAMPLES.value),
          ("sampler", _SAMPLER.value),
          ("steps", _STEPS.value),
      )
      if v is not None
  }
  if overrides:  # a replaced Predictor re-checks the sampler against the denoiser
    predictor = dataclasses.replace(
        predictor, sampling=dataclasses.replace(predictor.sampling, **overrides)
    )
  meta = export.export(predictor, _OUT.value, num_noise_ids=_NOISE_IDS.value, onnx=_ONNX.value)
  onnx = f", {export.ONNX_FILE}" if _ONNX.value else ""
  print(
      f"wrote {_OUT.value}: {export.PREDICT_FILE}, {export.DENOISER_FILE}{onnx}, "
      f"{export.MANIFEST_FILE} (sampling {meta['sampling']['sampler']}, "
      f"{meta['sampling']['steps']} steps, {meta['sampling']['num_samples']} samples)"
  )


if __name__ == "__main__":
  cli.run(main)
