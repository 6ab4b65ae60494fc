"""Models with random weights and random scenarios, for timings and for tests of what does not
depend on the weights (tracing, shapes, memory): a tokeniser bundle, a denoiser bundle, a
`Predictor` of both, and highway-like random observations."""

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from cvmdx_jax import constants
from cvmdx_jax.config.models import TokenizerConfig
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.data import from_arrays
from cvmdx_jax.data.scenarios import Scenarios
from cvmdx_jax.inference.bundles import Denoiser, TokenizerBundle
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.models import tokenizer as tokenizer_lib
from cvmdx_jax.models import uncertainty, unet1d


def random_tokenizer(config: TokenizerConfig, key: jax.Array) -> TokenizerBundle:
  """A `TokenizerBundle` of `config` with fresh parameters of `key`; each codebook entry's
  Gaussian of the latents is a unit one at the entry."""
  graphdef, params = tokenizer_lib.init_tokenizer(config, key)
  q, d = config.quantizer.codebook_size, config.encoder.latent_dim
  eye = jnp.broadcast_to(jnp.eye(d), (q, d, d))
  gaussians = uncertainty.Gaussians(params["codebook"], eye, eye, jnp.ones(q))
  return TokenizerBundle(
      params, gaussians, graphdef, config, ml_collections.FrozenConfigDict({"dataset_id": "none"})
  )


def random_denoiser(config: DiffusionRunConfig, key: jax.Array | None = None) -> Denoiser:
  """A `Denoiser` of `config` (sized for its tokens) with fresh parameters of `key` (default
  `jax.random.key(0)`)."""
  graphdef, params = unet1d.init_unet(config.model, jax.random.key(0) if key is None else key)
  return Denoiser(params, graphdef, config, ml_collections.FrozenConfigDict({}))


def random_predictor(
    tokenizer_config: TokenizerConfig,
    config: DiffusionRunConfig,
    sampling: SamplingConfig,
    chunk_size: int | None,
) -> Predictor:
  """A `Predictor` of a random tokeniser (key 0) and a random denoiser of `config` (key 1;
  `config` sized for the tokeniser's codebook, `with_tokens`)."""
  tokenizer = random_tokenizer(tokenizer_config, jax.random.key(0))
  denoiser = random_denoiser(config, jax.random.key(1))
  return Predictor(tokenizer, denoiser, sampling, chunk_size=chunk_size)


def random_scenarios(m: int, seed: int = 0) -> Scenarios:
  """`m` scenarios of highway-like random observations: every vehicle present, unit normal
  positions and velocities around 30 m/s along the road; zero futures, labels 0, 1, 2, ..."""
  rng = np.random.default_rng(seed)
  xi = rng.normal(0.0, 1.0, (m, constants.NUM_VEHICLES, constants.T_OBS, 4)).astype(np.float32)
  xi[..., 2] += 30.0
  zeros = np.zeros((m, constants.T_PRED, 2), np.float32)
  return from_arrays(
      xi=xi,
      mask=np.ones(xi.shape[:3], bool),
      future=zeros,
      controls=zeros,
      v0=np.full(m, 30.0, np.float32),
      psi0=np.zeros(m, np.float32),
      label=np.arange(m) % 3,
  )
