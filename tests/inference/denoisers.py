"""`Denoiser` bundles of freshly initialised U-Nets, for the tests of the sampling path."""

import ml_collections

from cvmdx_jax.config.denoiser import DenoiserConfig
from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.config.runs import DiffusionRunConfig
from cvmdx_jax.inference.bundles import Denoiser


def bundle(
    graphdef, params, unet: UNetConfig, diffusion: DenoiserConfig = DenoiserConfig()
) -> Denoiser:
  """The `Denoiser` of U-Net `unet` (graphdef, params) trained as `diffusion` says."""
  return Denoiser(
      params,
      graphdef,
      DiffusionRunConfig(model=unet, diffusion=diffusion),
      ml_collections.FrozenConfigDict({}),
  )
