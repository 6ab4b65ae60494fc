"""The one sampler entry point: each name is its sampler with the settings bound."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import diffusion
from cvmdx_jax.config.sampling import SAMPLERS
from cvmdx_jax.errors import UserError

SHAPE = (3, 8, 2)


def _v_fn(x_t, t):
  """A smooth stand-in for a network: v depends on x_t and t."""
  return 0.5 * x_t + 0.001 * t.astype(jnp.float32)[..., None, None]


@pytest.mark.parametrize(
    "name, direct",
    [
        (
            "ddim",
            lambda k, s: diffusion.ddim_sample(_v_fn, k, SHAPE, s, steps=4, eta=0.3, clip_x0=1.0),
        ),
        ("ddpm", lambda k, s: diffusion.ddpm_sample(_v_fn, k, SHAPE, s, clip_x0=1.0)),
        (
            "dpmpp2m",
            lambda k, s: diffusion.dpmpp_2m_sample(_v_fn, k, SHAPE, s, steps=4, clip_x0=1.0),
        ),
        ("distilled", lambda k, s: diffusion.distilled_sample(_v_fn, k, SHAPE, s, 4, clip_x0=1.0)),
    ],
)
def test_each_name_is_its_sampler_bit_for_bit(name, direct):
  schedule = diffusion.cosine_schedule(50)
  key = jax.random.key(3)
  sample = diffusion.get_sampler(name, steps=4, eta=0.3, clip_x0=1.0)
  np.testing.assert_array_equal(sample(_v_fn, key, SHAPE, schedule), direct(key, schedule))


def test_the_names_are_the_configs_and_others_are_refused():
  assert set(diffusion.SAMPLER_NAMES) == set(SAMPLERS)
  with pytest.raises(UserError, match="unipc"):
    diffusion.get_sampler("unipc", steps=3)
