"""The exported artefacts reproduce the in-package predictor and run without the package.

The models are untrained (:tiny configs, random parameters: the export does not depend on
the weights) with the demo's kind of denoiser: a guidance student with ego-motion FiLM,
residual controls and intent draws, sampled by the distilled sampler.
"""

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax import constants
from cvmdx_jax.config.runs import DiffusionRunConfig, TokenizerRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.data import from_arrays
from cvmdx_jax.inference import export
from cvmdx_jax.inference.bundles import Denoiser, TokenizerBundle
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models import uncertainty, unet1d
from cvmdx_jax.storage import checksums
from tests import subprocess_env

SCRIPT = subprocess_env.REPO / "experiments" / "run_exported.py"
# Float tolerance of the artefact against `Predictor` (m, m/s^2, rad/s): XLA compiles the
# artefact for the concrete batch with the parameters as constants and may fuse or fold
# other than the package's jit (on the CPUs measured the outputs were equal bit for bit)
ATOL = 1e-4


def _random_predictor() -> Predictor:
  tok_cfg = TokenizerRunConfig.from_config(tokenizer_config.get_config("tiny")).model
  graphdef, params = tokenizer_lib.init_tokenizer(tok_cfg, jax.random.key(0))
  q, d = tok_cfg.quantizer.codebook_size, tok_cfg.encoder.latent_dim
  eye = jnp.broadcast_to(jnp.eye(d), (q, d, d))
  tokenizer = TokenizerBundle(
      params,
      uncertainty.Gaussians(params["codebook"], eye, eye, jnp.ones(q)),
      graphdef,
      tok_cfg,
      ml_collections.FrozenConfigDict({"dataset_id": "none"}),
  )
  cfg = diffusion_config.get_config("tiny")
  cfg.diffusion.conditioning = "ego_film_residual"
  cfg.diffusion.intent_conditioning = True
  cfg.diffusion.guidance_input = True
  config = DiffusionRunConfig.from_config(cfg).with_tokens(q)
  graphdef, params = unet1d.init_unet(config.model, jax.random.key(1))
  denoiser = Denoiser(params, graphdef, config, ml_collections.FrozenConfigDict({}))
  return Predictor(
      tokenizer, denoiser, SamplingConfig(num_samples=4, sampler="distilled", steps=2), chunk_size=8
  )


def _scenarios(m: int):
  rng = np.random.default_rng(0)
  mask = (rng.random((m, constants.NUM_VEHICLES, constants.T_OBS)) > 0.2) | (
      np.arange(constants.T_OBS) == constants.T_OBS - 1
  )
  xi = rng.normal(0.0, 1.0, mask.shape + (4,)) * mask[..., None]
  zeros = np.zeros((m, constants.T_PRED, 2))
  return from_arrays(
      xi=xi,
      mask=mask,
      future=zeros,
      controls=zeros,
      v0=rng.uniform(20, 35, m),
      psi0=rng.uniform(-0.05, 0.05, m),
      label=np.arange(m) % 3,
  )


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
  predictor = _random_predictor()
  out = tmp_path_factory.mktemp("export")
  return predictor, out, export.export(predictor, out)


def _outputs(reference) -> dict:
  pred = reference.prediction
  return {
      "trajectories": pred.trajectories,
      "controls": pred.controls,
      "mean": pred.mean,
      "hypothesis_means": pred.hypotheses.means,
      "hypothesis_probs": pred.hypotheses.probs,
      "delta": reference.delta,
  }


def test_prediction_equals_predictor_for_two_batch_sizes(exported):
  predictor, out, _ = exported
  scenarios = _scenarios(5)
  reference = predictor(scenarios, seed=7)
  artefact = export.load(out)
  rows = np.array([1, 3])  # a batch of 2 through the same file: the rows' own keys
  for index in (np.arange(5), rows):
    got = artefact.call(*export.call_inputs(scenarios.take(index), 7, index[:, None]))
    np.testing.assert_array_equal(got["q"], reference.q[index])
    for name, want in _outputs(reference).items():
      np.testing.assert_allclose(got[name], want[index], atol=ATOL, rtol=0, err_msg=name)
  other_seed = artefact.call(*export.call_inputs(scenarios.take(rows), 8, rows[:, None]))
  assert np.abs(other_seed["trajectories"] - reference.prediction.trajectories[rows]).max() > 1e-3


def test_denoiser_equals_apply(exported):
  predictor, out, meta = exported
  b, cond_dim = 3, meta["denoiser"]["inputs"][3]["shape"][1]
  keys = jax.random.split(jax.random.key(2), 2)
  x_t = jax.random.normal(keys[0], (b, constants.T_PRED, 2))
  cond = jax.random.normal(keys[1], (b, cond_dim))
  t, q = jnp.array([0, 500, 999], jnp.int32), jnp.array([0, 1, 2], jnp.int32)
  got = export.load(out, export.DENOISER_FILE).call(x_t, t, q, cond)
  want = jax.jit(predictor.denoiser.apply)(x_t, t, q, cond)
  np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)


def test_manifest_names_the_symbolic_batch_and_a_corrupt_file_is_refused(exported):
  predictor, out, meta = exported
  assert json.loads((out / export.MANIFEST_FILE).read_text()) == meta
  assert [s["name"] for s in meta["predict"]["inputs"]] == [
      "xi",
      "mask",
      "v0",
      "psi0",
      "seed",
      "noise_ids",
  ]
  assert meta["predict"]["inputs"][5]["shape"] == ["b", 1]
  shapes = {s["name"]: s["shape"] for s in meta["predict"]["outputs"]}
  assert shapes["trajectories"] == ["b", 4, constants.T_PRED, 2]
  assert shapes["hypothesis_probs"][0] == "b" and shapes["q"] == ["b"]
  assert meta["denoiser"]["inputs"][3]["shape"] == ["b", predictor.denoiser.unet.cond_dim]
  assert meta["sampling"]["sampler"] == "distilled" and meta["sampling"]["steps"] == 2
  copy = out.parent / "corrupt"
  copy.mkdir()
  for name in (export.PREDICT_FILE, "checksums.json"):
    (copy / name).write_bytes((out / name).read_bytes())
  data = bytearray((copy / export.PREDICT_FILE).read_bytes())
  data[len(data) // 2] ^= 1
  (copy / export.PREDICT_FILE).write_bytes(bytes(data))
  with pytest.raises(checksums.CorruptRunError, match="predict.jax"):
    export.load(copy)


# Run in `python -I` (no PYTHONPATH, no user site), cvmdx_jax and configs made unimportable
_ISOLATED = """
import importlib.abc, runpy, sys
class Refuse(importlib.abc.MetaPathFinder):
  def find_spec(self, name, path=None, target=None):
    if name.split(".")[0] in ("cvmdx_jax", "configs", "tests"):
      raise ImportError(f"{name} is not available here")
sys.meta_path.insert(0, Refuse())
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
assert not any(m.split(".")[0] == "cvmdx_jax" for m in sys.modules)
"""


@pytest.mark.slow  # two fresh processes compile the artefact (~40 s of CPU)
def test_standalone_loader_runs_without_the_package(exported, tmp_path):
  predictor, out, _ = exported
  scenarios = _scenarios(3)
  np.savez(
      tmp_path / "in.npz",
      xi=scenarios.xi,
      mask=scenarios.mask,
      v0=scenarios.v0,
      psi0=scenarios.psi0,
  )
  cmd = [
      sys.executable,
      "-I",
      "-c",
      _ISOLATED,
      str(SCRIPT),
      f"--export_dir={out}",
      f"--inputs={tmp_path / 'in.npz'}",
      f"--out={tmp_path / 'pred.npz'}",
      "--seed=5",
  ]
  done = subprocess.run(
      cmd,
      capture_output=True,
      text=True,
      timeout=300,
      env=subprocess_env.environ(JAX_PLATFORMS="cpu"),
      cwd=tmp_path,
  )
  assert done.returncode == 0, done.stderr
  got = np.load(tmp_path / "pred.npz")
  reference = predictor(scenarios, seed=5)
  np.testing.assert_allclose(got["mean"], reference.mean, atol=ATOL, rtol=0)
  np.testing.assert_allclose(got["hypothesis_probs"], reference.hypotheses.probs, atol=ATOL)
  # a missing field: one line, exit 2, nothing written
  np.savez(tmp_path / "bad.npz", xi=scenarios.xi, mask=scenarios.mask, v0=scenarios.v0)
  bad = subprocess.run(
      cmd[:-3] + [f"--inputs={tmp_path / 'bad.npz'}", f"--out={tmp_path / 'bad_pred.npz'}"],
      capture_output=True,
      text=True,
      timeout=300,
      env=subprocess_env.environ(JAX_PLATFORMS="cpu"),
      cwd=tmp_path,
  )
  assert bad.returncode == 2 and "field 'psi0' missing" in bad.stderr.strip().splitlines()[-1]
  assert not (tmp_path / "bad_pred.npz").exists()


@pytest.mark.slow  # jax2onnx converts the U-Net equation by equation (~30 s)
# jax2onnx 0.17.1's flax plugin (third-party) reads `Variable.value`, deprecated by flax
@pytest.mark.filterwarnings("ignore:'.value' access is now deprecated:DeprecationWarning")
def test_onnx_denoiser_equals_the_package_in_onnx_runtime(tmp_path):
  pytest.importorskip(
      "jax2onnx", reason="optional: pip install --no-deps -r " "requirements-onnx.lock"
  )
  ort = pytest.importorskip("onnxruntime")
  predictor = _random_predictor()
  meta = export.export(predictor, tmp_path, onnx=True)
  assert meta["denoiser"]["onnx_file"] == export.ONNX_FILE
  session = ort.InferenceSession(checksums.read_bytes(tmp_path / export.ONNX_FILE))
  assert [i.name for i in session.get_inputs()] == ["x_t", "t", "q", "cond"]
  rng = np.random.default_rng(3)
  cond_dim = predictor.denoiser.unet.cond_dim
  for b in (4, 1):  # one model, two batch sizes
    feed = {
        "x_t": rng.normal(size=(b, constants.T_PRED, 2)).astype(np.float32),
        "t": rng.integers(0, 1000, b).astype(np.int32),
        "q": rng.integers(0, 3, b).astype(np.int32),
        "cond": rng.normal(size=(b, cond_dim)).astype(np.float32),
    }
    got = session.run(None, feed)[0]
    want = jax.jit(predictor.denoiser.apply)(*feed.values())
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)
