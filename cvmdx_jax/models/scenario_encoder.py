"""Encoder E and decoder D of the scenario tokeniser (Flax NNX).

E maps the encoder input of a scenario (9 vehicles x 75 steps x 5 channels: the
normalised [x, y, v_x, v_y] and the mask, `scenario_norm.encoder_input`) to a latent
z_hat (latent_dim,); D maps a (quantised) latent back to the normalised 9 x 75 x 4
features. Both treat the scenario as a 1-D sequence over time whose channels are the
9 vehicles' features, with strided convolutions down (75 -> 38 -> 19 -> 10 for three
levels) and nearest-neighbour upsampling + convolutions up.
"""

import jax
import jax.numpy as jnp
from flax import nnx

from cvmdx_jax import constants
from cvmdx_jax.config.models import EncoderConfig

_IN_CHANNELS = constants.NUM_VEHICLES * (constants.NUM_FEATURES + 1)
_OUT_CHANNELS = constants.NUM_VEHICLES * constants.NUM_FEATURES


class ScenarioEncoder(nnx.Module):
  """E: (B, 9, 75, 5) encoder input -> (B, latent_dim) z_hat."""

  def __init__(self, config: EncoderConfig, *, rngs: nnx.Rngs):
    widths = (_IN_CHANNELS, *config.channels)
    self.convs = nnx.List(
        [
            nnx.Conv(c_in, c_out, config.kernel_size, strides=2, rngs=rngs)
            for c_in, c_out in zip(widths[:-1], widths[1:])
        ]
    )
    self.out = nnx.Linear(
        config.bottleneck_steps() * config.channels[-1], config.latent_dim, rngs=rngs
    )

  def __call__(self, x: jax.Array) -> jax.Array:
    b = x.shape[0]
    h = jnp.transpose(x, (0, 2, 1, 3)).reshape(b, constants.T_OBS, _IN_CHANNELS)
    for conv in self.convs:
      h = nnx.gelu(conv(h))
    return self.out(h.reshape(b, -1))


class ScenarioDecoder(nnx.Module):
  """D: (B, latent_dim) latent -> (B, 9, 75, 4) normalised features."""

  def __init__(self, config: EncoderConfig, *, rngs: nnx.Rngs):
    self.steps = config.bottleneck_steps()
    widths = tuple(reversed(config.channels))
    self.inp = nnx.Linear(config.latent_dim, self.steps * widths[0], rngs=rngs)
    self.convs = nnx.List(
        [
            nnx.Conv(c_in, c_out, config.kernel_size, rngs=rngs)
            for c_in, c_out in zip(widths, (*widths[1:], widths[-1]))
        ]
    )
    self.out = nnx.Conv(widths[-1], _OUT_CHANNELS, config.kernel_size, rngs=rngs)

  def __call__(self, z: jax.Array) -> jax.Array:
    b = z.shape[0]
    h = nnx.gelu(self.inp(z)).reshape(b, self.steps, -1)
    for conv in self.convs:
      h = nnx.gelu(conv(jnp.repeat(h, 2, axis=1)))
    h = self.out(h[:, : constants.T_OBS])
    h = h.reshape(b, constants.T_OBS, constants.NUM_VEHICLES, constants.NUM_FEATURES)
    return jnp.transpose(h, (0, 2, 1, 3))
