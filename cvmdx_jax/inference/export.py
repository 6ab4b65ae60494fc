"""Serialised `jax.export` artefacts of a `Predictor`: the model outside this package.

`export(predictor, out_dir)` writes three files, four with `onnx` (one group,
`storage.checksums.write_all`: all new or all old, listed with their sha256 in
`checksums.json`):

    predict.jax      the whole prediction: tokeniser, sampler, vehicle motion model and
                     hypotheses, `export_functions.predict_fn` (inputs and outputs:
                     `predict_inputs`, `PREDICT_OUTPUTS`)
    denoiser.jax     one evaluation of the denoiser v(x_t, t, q[, cond]), `denoiser_fn`
    manifest.json    names, shapes ("b" the symbolic batch) and dtypes of both, the sampling
                     settings, the runs the parameters come from, the delta limit
    denoiser.onnx    with `onnx=True`: the same denoiser as ONNX (opset 23, by jax2onnx, an
                     optional dependency: requirements-onnx.lock), dynamic batch "b"; the
                     solver and its steps stay outside (the manifest's sampling settings)

Each artefact is `jax.export.export(jax.jit(f))` over a symbolic batch dimension b, so one
file serves any batch size; the parameters (the denoiser's prepared as `Predictor` applies
them) are baked in as constants, so a user needs the bytes and JAX alone:

    exported = jax.export.deserialize(open("predict.jax", "rb").read())
    out = exported.call(xi, mask, v0, psi0, np.uint32(seed), noise_ids)

Scenario i of a call draws its noise from fold_in(... fold_in(key(seed), noise_ids[i, 0])
..., noise_ids[i, K - 1]), as `Predictor` does (`noise_ids`; K = 1 and the scenario's
position by default, K = 2 (frame, track id) in `inference.stream`; K is fixed at export,
`num_noise_ids`), so the artefact reproduces a `Predictor` call
(to float rounding: XLA compiles the artefact for the concrete batch with the parameters
as constants, and may fold or fuse other than the package's jit; tests/inference/
test_export.py states the tolerance). The artefacts are lowered for the backend they are
exported on (`jax.default_backend()`, which also picks the U-Net's fast paths).
"""

import dataclasses
import os
from pathlib import Path

import jax
import numpy as np

from cvmdx_jax import constants, ego_motion
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference import predictor as predictor_lib
from cvmdx_jax.inference.export_functions import (
    BATCH,
    abstract_inputs,
    denoiser_fn,
    denoiser_inputs,
    predict_fn,
    predict_inputs,
)
from cvmdx_jax.models import performance
from cvmdx_jax.storage import atomic, checksums, identity

PREDICT_FILE = "predict.jax"
DENOISER_FILE = "denoiser.jax"
ONNX_FILE = "denoiser.onnx"
MANIFEST_FILE = "manifest.json"
FORMAT_VERSION = 1


def _spec(name, shape, dtype) -> dict:
  return {
      "name": name,
      "shape": [str(d) if not isinstance(d, int) else d for d in shape],
      "dtype": str(dtype),
  }


def export_bytes(f, inputs) -> tuple[bytes, list]:
  """(serialised `jax.export` of jit(f) over `inputs` with a symbolic batch, the output
  specs [{name, shape, dtype}] in the artefact's flat output order)."""
  (batch,) = jax.export.symbolic_shape(BATCH)
  exported = jax.export.export(jax.jit(f), platforms=(jax.default_backend(),))(
      *abstract_inputs(inputs, batch)
  )
  outputs = [
      _spec(n, a.shape, a.dtype) for n, a in zip(_output_names(exported), exported.out_avals)
  ]
  return exported.serialize(), outputs


def _output_names(exported) -> list[str]:
  """Names of the flat outputs: the dict keys of a dict output, else "v"."""
  positions = jax.tree.unflatten(exported.out_tree, range(len(exported.out_avals)))
  return sorted(positions, key=positions.get) if isinstance(positions, dict) else ["v"]


def _runs(predictor: predictor_lib.Predictor) -> dict:
  tok = predictor.tokenizer
  checkpoint = None if tok.checkpoint is None else tok.checkpoint.to_dict()
  return {
      "tokenizer_checkpoint": checkpoint,
      "denoiser_fingerprint_id": identity.content_id(predictor.denoiser.fingerprint.to_dict()),
      "denoiser_params_id": identity.content_id(jax.device_get(predictor.denoiser.params)),
  }


def manifest(
    predictor: predictor_lib.Predictor, predict_inputs_, predict_outputs, denoiser_outputs
) -> dict:
  """The manifest.json of an export (see the module docstring)."""
  targets = predictor.denoiser.config.diffusion
  return {
      "format_version": FORMAT_VERSION,
      "jax_version": jax.__version__,
      "platforms": [jax.default_backend()],
      "batch_dimension": BATCH,
      "predict": {
          "file": PREDICT_FILE,
          "inputs": [_spec(*i) for i in predict_inputs_],
          "outputs": predict_outputs,
          "keys": "scenario i draws from fold_in(... fold_in(key(seed), "
          "noise_ids[i, 0]) ..., noise_ids[i, K - 1])",
      },
      "denoiser": {
          "file": DENOISER_FILE,
          "inputs": [_spec(*i) for i in denoiser_inputs(predictor)],
          "outputs": denoiser_outputs,
          "cond": _cond_layout(predictor),
          "num_steps": targets.num_steps,
          "null_token": predictor.denoiser.null_token,
          "control_scale": list(np.asarray(targets.control_scale, float).ravel()),
          "conditioning": targets.conditioning,
      },
      "sampling": _plain(dataclasses.asdict(predictor.sampling)),
      "delta_limit": predictor.delta_limit if np.isfinite(predictor.delta_limit) else None,
      "runs": _runs(predictor),
  }


def _cond_layout(predictor) -> list[str]:
  """What the columns of the denoiser's cond hold, in order."""
  targets = predictor.denoiser.config.diffusion
  parts = []
  if ego_motion.uses_film(targets.conditioning) or targets.intent_conditioning:
    parts.append(f"ego_motion features ({ego_motion.NUM_FEATURES})")
  if targets.intent_conditioning:
    parts.append(f"intent one-hot ({constants.NUM_CLASSES})")
  if targets.guidance_input:
    parts.append("guidance weight w (1)")
  return parts


def _plain(value):
  """JSON-able copy of a nested dict of settings (tuples as lists)."""
  if isinstance(value, dict):
    return {k: _plain(v) for k, v in value.items()}
  if isinstance(value, (tuple, list)):
    return [_plain(v) for v in value]
  return value


def onnx_bytes(predictor: predictor_lib.Predictor) -> bytes:
  """`denoiser_fn` as an ONNX model with a dynamic batch. jax2onnx has no lowering of
  `lax.platform_dependent`, so the U-Net's paths are fixed while it traces: the Winograd
  convolutions that `Predictor` runs on a CPU (its prepared kernels), the plain group norm
  (the fast one differs only in the backward pass)."""
  try:
    import jax2onnx  # optional: pip install --no-deps -r requirements-onnx.lock
  except ImportError as e:
    raise UserError(
        "the ONNX export needs jax2onnx and onnx: pip install --no-deps -r "
        f"requirements-onnx.lock ({e})"
    ) from e
  inputs = denoiser_inputs(predictor)
  (batch,) = jax.export.symbolic_shape(BATCH)
  with performance.use(performance.PerformanceOptions(winograd="on", group_norm_backward="off")):
    model = jax2onnx.to_onnx(
        denoiser_fn(predictor),
        abstract_inputs(inputs, batch),
        model_name="cvmdx_denoiser",
        input_names=[n for n, _, _ in inputs],
        output_names=["v"],
    )
  return model.SerializeToString()


def export(
    predictor: predictor_lib.Predictor,
    out_dir: str | os.PathLike,
    num_noise_ids: int = 1,
    onnx: bool = False,
) -> dict:
  """Writes predict.jax, denoiser.jax, manifest.json (and denoiser.onnx) to `out_dir`
  (created); returns the manifest. num_noise_ids: K of the noise_ids input (1:
  `Predictor`'s default ids)."""
  out = Path(out_dir)
  out.mkdir(parents=True, exist_ok=True)
  files = {out / ONNX_FILE: onnx_bytes(predictor)} if onnx else {}
  inputs = predict_inputs(num_noise_ids)
  predict_bytes, predict_outputs = export_bytes(predict_fn(predictor), inputs)
  denoiser_bytes, denoiser_outputs = export_bytes(
      denoiser_fn(predictor), denoiser_inputs(predictor)
  )
  meta = manifest(predictor, inputs, predict_outputs, denoiser_outputs)
  if onnx:
    meta["denoiser"]["onnx_file"] = ONNX_FILE
  checksums.write_all(
      {
          out / PREDICT_FILE: predict_bytes,
          out / DENOISER_FILE: denoiser_bytes,
          **files,
          out / MANIFEST_FILE: atomic.json_text(meta).encode(),
      }
  )
  return meta


def load(out_dir: str | os.PathLike, name: str = PREDICT_FILE) -> jax.export.Exported:
  """The deserialised artefact `name` of an export directory (checksum verified)."""
  return jax.export.deserialize(checksums.read_bytes(Path(out_dir) / name))


def call_inputs(scenarios, seed: int, noise_ids=None) -> tuple:
  """predict.jax's positional inputs for `Scenarios` or `Observations` (noise_ids (M, K);
  default the positions 0..M-1, K = 1)."""
  ids = np.arange(len(scenarios))[:, None] if noise_ids is None else noise_ids
  return (
      np.asarray(scenarios.xi, np.float32),
      np.asarray(scenarios.mask, bool),
      np.asarray(scenarios.v0, np.float32),
      np.asarray(scenarios.psi0, np.float32),
      np.uint32(seed),
      np.asarray(ids, np.uint32),
  )
