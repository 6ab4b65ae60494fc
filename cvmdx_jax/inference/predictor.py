"""The library entry point: a `Predictor` from trained tokeniser + denoiser runs.

    predictor = Predictor.load("runs/demo/tokenizer", "runs/demo/diffusion")
    out = predictor(scenarios, seed=0)   # any reader's `Scenarios`
    out.mean, out.hypotheses.means, out.hypotheses.probs

Scenarios whose uncertainty delta exceeds the largest delta of the tokeniser's training
split are flagged (`PredictorOutput.out_of_distribution`) and reported with an
`OutOfDistributionWarning`: their prediction extrapolates beyond the training data.

Inputs are checked against the highD reader's bounds (`predictor_inputs.check_inputs`): a
seed outside [0, 2**32), an ego absent at t0, |psi0| > pi or v0 above the reader's speed
bound is a ValueError naming the scenario and field; an ego velocity at t0 that the reader
would have refused by its components (against the road direction, or laterally beyond
20 m/s) is an `UnusualScenarioWarning`.

One jitted call per chunk goes from observed scenarios to tokens, uncertainty,
guided DDIM samples, VMM trajectories and GMM/BIC hypotheses; it is the only jit on the
path (the functions it calls are plain, jittable code) and compiles once per chunk
shape. Chunks are split over all visible devices (`jax.sharding`); the parameters are
replicated once, when the `Predictor` is made. Scenario i always draws its noise from
`fold_in(key(seed), i)`, so results do not depend on the chunk size or device count, to
float rounding (chunks of other shapes compile to other kernels; ~1e-5 m).
"""

import dataclasses
import functools
import math
import numbers
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from cvmdx_jax import ego_motion, sharding
from cvmdx_jax.config.sampling import SamplingConfig, check_sampling
from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.diffusion import cosine_schedule
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference.bundles import Denoiser, TokenizerBundle, load_denoiser, load_tokenizer
from cvmdx_jax.inference.observations import Observations
from cvmdx_jax.inference.predictor_inputs import check_inputs, check_student_steps
from cvmdx_jax.inference.sampling import Prediction, predict_batch
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import tokens as tokens_lib
from cvmdx_jax.storage import identity


class IncompatibleRunsError(UserError):
  """The tokeniser and the denoiser were not trained together."""


class OutOfDistributionWarning(UserWarning):
  """Some scenarios lie beyond the tokeniser's training range (delta above its maximum)."""


@dataclasses.dataclass(frozen=True)
class PredictorOutput:
  """Predictions for M scenarios (numpy).

  Attributes:
    prediction: `Prediction` with controls / trajectories (M, N, 125, 2), mean
      (M, 125, 2) and hypotheses (means (M, C_max, 125, 2), probs (M, C_max)).
    q: (M,) scenario tokens; delta: (M,) Mahalanobis uncertainty.
    out_of_distribution: (M,) bool, delta above `Predictor.delta_limit` (or not finite).
  """

  prediction: Prediction
  q: np.ndarray
  delta: np.ndarray
  out_of_distribution: np.ndarray

  @property
  def mean(self):
    return self.prediction.mean

  @property
  def hypotheses(self):
    return self.prediction.hypotheses


@functools.partial(jax.jit, static_argnames="config")
def _predict(
    tokenizer: TokenizerBundle,
    denoiser: Denoiser,
    xi,
    mask,
    v0,
    psi0,
    keys,
    schedule,
    *,
    config: SamplingConfig,
):
  q, _, delta = tokenizer.tokenize(xi, mask)
  conditioning = denoiser.config.diffusion.conditioning
  ego = None if conditioning == "token" else ego_motion.ego_features(xi, mask)
  pred = predict_batch(denoiser, q, delta, v0, psi0, keys, ego, schedule=schedule, config=config)
  return pred, q, delta


def _fold_ids(key, ids):
  """fold_in of `key` with each of `ids` (K,) in turn."""
  for k in range(ids.shape[0]):
    key = jax.random.fold_in(key, ids[k])
  return key


SCENARIOS_PER_CALL = 256  # the most scenarios a call holds by default
# the most sampled trajectories (scenarios x N) a call holds by default: the paper's N = 9 at
# 256 scenarios (N = 64: 36 scenarios, 0.43 GB less peak memory than 64 in `make demo`'s
# evaluation, not slower; docs/log/2026-12-06-demo-time.md)
SAMPLES_PER_CALL = 2304


def default_chunk(num_samples: int) -> int:
  """Scenarios per call by default: 256, fewer where N samples each would exceed
  `SAMPLES_PER_CALL` trajectories (N = 9: 256, N = 64: 36)."""
  return max(1, min(SCENARIOS_PER_CALL, SAMPLES_PER_CALL // num_samples))


@dataclasses.dataclass(frozen=True)
class Predictor:
  """Trained cVMDx: tokeniser bundle + denoiser + sampling settings.

  What `load` has read stays here, so that nothing needs reading twice:
    tokenizer: the `TokenizerBundle` (parameters, per-entry Gaussians of delta in
      `tokenizer.gaussians`, model config, fingerprint, checkpoint {fingerprint, step,
      params_id}).
    denoiser: the `Denoiser` (EMA parameters, its `DiffusionRunConfig` in
      `denoiser.config`, fingerprint).
    sampling: the `SamplingConfig` used (default: the diffusion run's).
    train_tokens: the tokeniser's train-split `runs.tokens.Tokens` (q, z_hat, delta; None
      for a `Predictor` built from bundles).
    delta_limit: the largest delta over the train split; scenarios above it are out of
      distribution (the default, inf, flags none).
    chunk_size: scenarios per jitted call; None: `default_chunk(num_samples)`, at most
      `SAMPLES_PER_CALL` sampled trajectories a call, so that a call's memory is bounded
      by its samples whatever N (the demo's N = 64: 64 scenarios, ~0.65 GiB of XLA
      temporaries, against ~2.6 GiB for 256; docs/log/2026-12-06-speed.md).

  On construction the denoiser's parameters are prepared for inference
  (`unet1d.prepare_params`: the Winograd kernels transformed once, not in every call; the
  same predictions bit for bit) and the tokeniser's and the denoiser's arrays are replicated
  over the devices of `sharding.data_mesh()` (once; `dataclasses.replace` keeps them there).
  The sampling settings are checked against the denoiser (`config.sampling.check_sampling`).
  """

  tokenizer: TokenizerBundle
  denoiser: Denoiser
  sampling: SamplingConfig
  chunk_size: int | None = None
  delta_limit: float = math.inf
  train_tokens: tokens_lib.Tokens | None = None

  def __post_init__(self):
    if self.chunk_size is not None:
      if (
          isinstance(self.chunk_size, bool)
          or not isinstance(self.chunk_size, numbers.Integral)
          or self.chunk_size < 1
      ):
        raise UserError(
            f"chunk_size={self.chunk_size!r}: expected a positive whole number of "
            "scenarios per call (or None: bounded by samples)"
        )
      object.__setattr__(self, "chunk_size", int(self.chunk_size))
    check_sampling(self.sampling, self.denoiser.config.diffusion)
    check_student_steps(self.sampling, self.denoiser.fingerprint)
    mesh = sharding.data_mesh()
    denoiser = dataclasses.replace(
        self.denoiser, params=unet1d.prepare_params(self.denoiser.graphdef, self.denoiser.params)
    )
    object.__setattr__(self, "tokenizer", sharding.replicate(self.tokenizer, mesh))
    object.__setattr__(self, "denoiser", sharding.replicate(denoiser, mesh))

  @property
  def scenarios_per_call(self) -> int:
    """`chunk_size`, or `default_chunk` of the sampling's N where it is None."""
    return self.chunk_size or default_chunk(self.sampling.num_samples)

  @classmethod
  def load(
      cls,
      tokenizer_dir,
      diffusion_dir,
      sampling: SamplingConfig | None = None,
      chunk_size: int | None = None,
  ) -> "Predictor":
    """Loads both runs and checks that they belong together: the denoiser must have been
    trained on tokens of exactly this tokeniser checkpoint (its fingerprint, which includes
    the dataset id, its step and the content id of its parameters).

    Args:
      tokenizer_dir, diffusion_dir: the two run directories.
      sampling: sampling settings; default: the diffusion run's (`config.sampling`).
      chunk_size: scenarios per jitted call (None: `default_chunk`).

    Raises:
      IncompatibleRunsError: the denoiser was trained on tokens of another tokeniser
        checkpoint (the message names the differing keys).
    """
    bundle = load_tokenizer(tokenizer_dir)
    denoiser = load_denoiser(diffusion_dir)
    identity.check(
        denoiser.fingerprint.to_dict()["tokenizer"],
        bundle.checkpoint.to_dict(),
        f"denoiser {diffusion_dir} (not trained on tokens of tokeniser " f"{tokenizer_dir})",
        IncompatibleRunsError,
    )
    sampling = sampling or denoiser.config.sampling
    train, _ = tokens_lib.load_tokens(tokens_lib.tokens_path(tokenizer_dir, "train"))
    return cls(
        tokenizer=bundle,
        denoiser=denoiser,
        sampling=sampling,
        chunk_size=chunk_size,
        delta_limit=float(np.max(train.delta)),
        train_tokens=train,
    )

  def __call__(
      self, scenarios: Scenarios | Observations, seed: int = 0, noise_ids=None
  ) -> PredictorOutput:
    """Predicts every scenario; see the module docstring; inputs as `check_inputs`.

    `scenarios`: `Scenarios` or `Observations` (what is known at t0: fields xi, mask, v0,
    psi0). `noise_ids`: (M, K) ints in [0, 2**32); scenario i draws from fold_in(...
    fold_in(key(seed), noise_ids[i, 0]) ..., noise_ids[i, K - 1]); None = (i,), the
    module docstring's. (frame, track_id) makes a vehicle's draw at a frame independent
    of the other vehicles and frames predicted with it (`inference.stream`).
    """
    check_inputs(scenarios, seed)
    ids = np.arange(len(scenarios))[:, None] if noise_ids is None else np.asarray(noise_ids)
    if ids.ndim != 2 or len(ids) != len(scenarios) or np.any((ids < 0) | (ids >= 2**32)):
      raise ValueError(
          f"noise_ids: expected (M, K) ints in [0, 2**32) with M = "
          f"{len(scenarios)}, got shape {ids.shape}"
      )
    ids = ids.astype(np.uint32)
    mesh = sharding.data_mesh()
    chunk = -(-self.scenarios_per_call // mesh.size) * mesh.size
    m = len(scenarios)
    chunk = min(chunk, -(-m // mesh.size) * mesh.size)
    base = jax.random.key(int(seed))
    schedule = cosine_schedule(self.denoiser.config.diffusion.num_steps)
    outputs = []
    for start in tqdm(range(0, m, chunk), desc="predict", unit="chunk", disable=m <= chunk):
      idx = np.arange(start, min(start + chunk, m))
      inputs = {
          "xi": np.asarray(scenarios.xi[idx], np.float32),
          "mask": np.asarray(scenarios.mask[idx], bool),
          "v0": np.asarray(scenarios.v0[idx], np.float32),
          "psi0": np.asarray(scenarios.psi0[idx], np.float32),
          "index": ids[idx],
      }
      padded, weight = sharding.pad_batch(inputs, chunk)
      keys = jax.vmap(functools.partial(_fold_ids, base))(jnp.asarray(padded.pop("index")))
      batch = sharding.shard_batch({**padded, "keys": keys}, mesh)
      out = _predict(
          self.tokenizer,
          self.denoiser,
          batch["xi"],
          batch["mask"],
          batch["v0"],
          batch["psi0"],
          batch["keys"],
          schedule,
          config=self.sampling,
      )
      n = int(weight.sum())
      outputs.append(jax.tree.map(lambda a: np.asarray(a)[:n], out))
    pred, q, delta = jax.tree.map(lambda *xs: np.concatenate(xs), *outputs)
    ood = ~(delta <= self.delta_limit)
    if ood.any():
      warnings.warn(
          f"{int(ood.sum())} of {m} scenarios have an uncertainty delta beyond the "
          f"tokeniser's training range (max {self.delta_limit:.3g}); their "
          f"predictions extrapolate: scenarios {np.flatnonzero(ood)[:20].tolist()}"
          f"{' ...' if ood.sum() > 20 else ''}",
          OutOfDistributionWarning,
          stacklevel=2,
      )
    return PredictorOutput(prediction=pred, q=q, delta=delta, out_of_distribution=ood)
