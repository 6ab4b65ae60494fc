"""The library entry point: a `Predictor` from trained tokeniser + denoiser runs.

    predictor = Predictor.load("runs/demo/tokenizer", "runs/demo/diffusion")
    out = predictor(scenarios, seed=0)   # any reader's `Scenarios`
    out.mean, out.hypotheses.means, out.hypotheses.probs

One jitted call per chunk goes from observed scenarios to tokens, uncertainty,
guided DDIM samples, VMM trajectories and GMM/BIC hypotheses. Chunks are split over
all visible devices (`jax.sharding`). Scenario i always draws its noise from
`fold_in(key(seed), i)`, so results do not depend on the chunk size or device count.
"""

import dataclasses
import functools
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from cvmdx_jax import constants, ego_motion, sharding
from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.diffusion import cosine_schedule
from cvmdx_jax.inference import Prediction, SamplingConfig, predict_batch
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import tokenizer as tokenizer_train


class IncompatibleRunsError(ValueError):
  """The tokeniser and the denoiser were not trained together."""


@dataclasses.dataclass(frozen=True)
class PredictorOutput:
  """Predictions for M scenarios (numpy).

  Attributes:
    prediction: `Prediction` with controls / trajectories (M, N, 125, 2), mean
      (M, 125, 2) and hypotheses (means (M, C_max, 125, 2), probs (M, C_max)).
    q: (M,) scenario tokens; delta: (M,) Mahalanobis uncertainty.
  """

  prediction: Prediction
  q: np.ndarray
  delta: np.ndarray

  @property
  def mean(self):
    return self.prediction.mean

  @property
  def hypotheses(self):
    return self.prediction.hypotheses


@functools.partial(jax.jit, static_argnames=("null_token", "config"))
def _predict(bundle, graphdef_params, xi, mask, v0, psi0, keys, schedule, *, null_token,
             config):
  graphdef, params = graphdef_params
  q, _, delta = tokenizer_train.tokenize(bundle, xi, mask)
  ego = None if config.conditioning == "token" else ego_motion.ego_features(xi, mask)
  pred = predict_batch(graphdef, params, q, delta, v0, psi0, keys, ego, schedule=schedule,
                       null_token=null_token, config=config)
  return pred, q, delta


def check_scenarios(scenarios: Scenarios, source: str = "scenarios") -> None:
  """Raises ValueError for wrong shapes or non-finite inputs of the fields the model reads."""
  n, t, f = constants.NUM_VEHICLES, constants.T_OBS, constants.NUM_FEATURES
  m = len(scenarios)
  expected = {"xi": (m, n, t, f), "mask": (m, n, t), "v0": (m,), "psi0": (m,)}
  for name, shape in expected.items():
    value = np.asarray(getattr(scenarios, name))
    if value.shape != shape:
      raise ValueError(f"{source}: field '{name}' has shape {value.shape}, expected {shape}")
    if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
      bad = np.argwhere(~np.isfinite(value.reshape(m, -1)).all(-1))[0, 0]
      raise ValueError(f"{source}: field '{name}' holds NaN/inf (scenario {bad})")
  if m == 0:
    raise ValueError(f"{source}: no scenarios")


@dataclasses.dataclass(frozen=True)
class Predictor:
  """Trained cVMDx: tokeniser bundle + denoiser + sampling settings."""

  tokenizer: tokenizer_train.TokenizerBundle
  denoiser: diffusion_train.Denoiser
  sampling: SamplingConfig
  chunk_size: int = 256

  @classmethod
  def load(cls, tokenizer_dir, diffusion_dir, sampling: SamplingConfig | None = None,
           chunk_size: int = 256) -> "Predictor":
    """Loads both runs and checks that they belong together.

    Raises:
      IncompatibleRunsError: the denoiser was trained on tokens of another tokeniser
        checkpoint, or its token count differs from the codebook size.
    """
    bundle = tokenizer_train.load_tokenizer(tokenizer_dir)
    denoiser = diffusion_train.load_denoiser(diffusion_dir)
    used = denoiser.fingerprint.get("tokenizer", {}).get("fingerprint")
    given = json.loads((Path(tokenizer_dir) / tokenizer_train.CONFIG_NAME).read_text())
    given = given["fingerprint"]
    q = bundle.config.quantizer.codebook_size
    if denoiser.unet.num_tokens != q or used != given:
      differing = sorted(k for k in set(used or {}) | set(given)
                         if (used or {}).get(k) != given.get(k))
      raise IncompatibleRunsError(
          f"denoiser {diffusion_dir} was not trained on tokens of tokeniser {tokenizer_dir}: "
          f"it has {denoiser.unet.num_tokens} tokens vs codebook size {q}; differing "
          f"tokeniser fingerprint keys: {differing}")
    trained = diffusion_train.sampling_config(denoiser.config)
    sampling = dataclasses.replace(sampling or trained, control_scale=trained.control_scale,
                                   conditioning=trained.conditioning,
                                   residual_decay_s=trained.residual_decay_s)
    return cls(tokenizer=bundle, denoiser=denoiser, sampling=sampling, chunk_size=chunk_size)

  def __call__(self, scenarios: Scenarios, seed: int = 0) -> PredictorOutput:
    """Predicts every scenario; see the module docstring."""
    check_scenarios(scenarios)
    mesh = sharding.data_mesh()
    chunk = -(-self.chunk_size // mesh.size) * mesh.size
    m = len(scenarios)
    chunk = min(chunk, -(-m // mesh.size) * mesh.size)
    base = jax.random.key(seed)
    schedule = cosine_schedule(self.denoiser.config.diffusion.num_steps)
    params = sharding.replicate((self.denoiser.graphdef, self.denoiser.params), mesh)
    bundle = sharding.replicate(self.tokenizer, mesh)
    outputs = []
    for start in tqdm(range(0, m, chunk), desc="predict", unit="chunk", disable=m <= chunk):
      idx = np.arange(start, min(start + chunk, m))
      inputs = {"xi": np.asarray(scenarios.xi[idx], np.float32),
                "mask": np.asarray(scenarios.mask[idx], bool),
                "v0": np.asarray(scenarios.v0[idx], np.float32),
                "psi0": np.asarray(scenarios.psi0[idx], np.float32), "index": idx}
      padded, weight = sharding.pad_batch(inputs, chunk)
      keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.asarray(padded.pop("index")))
      batch = sharding.shard_batch({**padded, "keys": keys}, mesh)
      out = _predict(bundle, params, batch["xi"], batch["mask"], batch["v0"], batch["psi0"],
                     batch["keys"], schedule, null_token=self.denoiser.unet.null_token,
                     config=self.sampling)
      n = int(weight.sum())
      outputs.append(jax.tree.map(lambda a: np.asarray(a)[:n], out))
    pred, q, delta = jax.tree.map(lambda *xs: np.concatenate(xs), *outputs)
    return PredictorOutput(prediction=pred, q=q, delta=delta)
