"""The hand-written GroupNorm (forward and backward) and the plain path of the
`group_norm_backward` option against a two-pass reference, and the
phase-split upsampling against the repeat-then-convolve it replaces."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from cvmdx_jax.models import layers
from cvmdx_jax.models.group_norm import (
    GroupNorm,
    group_norm,
    group_norm_silu,
    plain_group_norm,
    plain_group_norm_silu,
)


def _reference(x, scale, bias, groups, eps):
  """GroupNorm as written in the paper of Wu & He: two-pass variance, no tricks."""
  b, length, c = x.shape
  xg = x.reshape(b, length, groups, c // groups)
  mean = xg.mean(axis=(1, 3), keepdims=True)
  var = ((xg - mean) ** 2).mean(axis=(1, 3), keepdims=True)
  return ((xg - mean) / jnp.sqrt(var + eps)).reshape(b, length, c) * scale + bias


@pytest.mark.parametrize("norm", [group_norm, plain_group_norm])  # fast and plain paths
@pytest.mark.parametrize("shape,groups", [((3, 16, 64), 8), ((2, 5, 12), 4), ((1, 7, 6), 6)])
def test_forward_and_gradients_match_the_reference(shape, groups, norm):
  keys = jax.random.split(jax.random.key(0), 4)
  x = 2.0 * jax.random.normal(keys[0], shape) + 1.5
  scale = jax.random.normal(keys[1], shape[-1:])
  bias = jax.random.normal(keys[2], shape[-1:])
  weight = jax.random.normal(keys[3], shape)
  np.testing.assert_allclose(
      norm(x, scale, bias, groups, 1e-5), _reference(x, scale, bias, groups, 1e-5), atol=2e-5
  )
  # a non-linear read-out, so that every term of the backward pass matters
  ours = lambda *a: jnp.sum(weight * jnp.sin(norm(*a, groups, 1e-5)))
  ref = lambda *a: jnp.sum(weight * jnp.sin(_reference(*a, groups, 1e-5)))
  for g_ours, g_ref in zip(
      jax.grad(ours, (0, 1, 2))(x, scale, bias), jax.grad(ref, (0, 1, 2))(x, scale, bias)
  ):
    np.testing.assert_allclose(g_ours, g_ref, atol=5e-5 * float(jnp.abs(g_ref).max()))


def test_module_has_the_nnx_parameter_names_and_initial_values():
  norm = GroupNorm(8, 4, 1e-5)
  assert set(nnx.to_pure_dict(nnx.state(norm, nnx.Param))) == {"scale", "bias"}
  x = jax.random.normal(jax.random.key(1), (2, 3, 8))
  np.testing.assert_allclose(norm(x), _reference(x, 1.0, 0.0, 4, 1e-5), atol=2e-5)


def test_channels_not_divisible_by_groups_are_refused():
  with pytest.raises(ValueError, match="6 channels are not divisible by 4 groups"):
    GroupNorm(6, 4, 1e-5)


def test_upsample_equals_repeat_then_convolve():
  up = layers.Upsample(5, rngs=nnx.Rngs(0))
  up.conv.kernel[...] = jax.random.normal(jax.random.key(2), (3, 5, 5))
  up.conv.bias[...] = jax.random.normal(jax.random.key(3), (5,))
  x = jax.random.normal(jax.random.key(4), (2, 8, 5))
  want = up.conv(jnp.repeat(x, 2, axis=1))  # the official Upsample: nearest, then conv
  np.testing.assert_allclose(up(x), want, atol=1e-5)
  # and its gradients, through the parameters of that convolution
  graphdef, params = nnx.split(up, nnx.Param)
  params = nnx.to_pure_dict(params)
  ours = lambda p, x: jnp.sum(jnp.cos(nnx.merge(graphdef, p)(x)))
  ref = lambda p, x: jnp.sum(
      jnp.cos(
          jax.lax.conv_general_dilated(
              jnp.repeat(x, 2, axis=1),
              p["conv"]["kernel"],
              (1,),
              ((1, 1),),
              dimension_numbers=("NWC", "WIO", "NWC"),
          )
          + p["conv"]["bias"]
      )
  )
  for a, b in zip(
      jax.tree.leaves(jax.grad(ours, (0, 1))(params, x)),
      jax.tree.leaves(jax.grad(ref, (0, 1))(params, x)),
  ):
    np.testing.assert_allclose(a, b, atol=1e-4)


@pytest.mark.parametrize("norm_silu", [group_norm_silu, plain_group_norm_silu])
def test_fused_silu_with_modulation_matches_the_reference(norm_silu):
  keys = jax.random.split(jax.random.key(7), 6)
  x = 1.5 * jax.random.normal(keys[0], (3, 10, 16)) - 0.5
  scale, bias = jax.random.normal(keys[1], (16,)), jax.random.normal(keys[2], (16,))
  m, c = 1.0 + 0.3 * jax.random.normal(keys[3], (3, 16)), jax.random.normal(keys[4], (3, 16))
  weight = jax.random.normal(keys[5], x.shape)
  ref_out = lambda x, s, b, m, c: jax.nn.silu(
      _reference(x, s, b, 4, 1e-5) * m[:, None] + c[:, None]
  )
  ours_out = lambda x, s, b, m, c: norm_silu(x, s, b, m, c, 4, 1e-5)
  args = (x, scale, bias, m, c)
  np.testing.assert_allclose(ours_out(*args), ref_out(*args), atol=2e-5)
  ours = lambda *a: jnp.sum(weight * jnp.sin(ours_out(*a)))
  ref = lambda *a: jnp.sum(weight * jnp.sin(ref_out(*a)))
  for g_ours, g_ref in zip(jax.grad(ours, range(5))(*args), jax.grad(ref, range(5))(*args)):
    np.testing.assert_allclose(g_ours, g_ref, atol=5e-5 * float(jnp.abs(g_ref).max()))
  # the module's default modulation is none
  norm = GroupNorm(16, 4, 1e-5)
  np.testing.assert_allclose(norm.silu(x), jax.nn.silu(_reference(x, 1.0, 0.0, 4, 1e-5)), atol=2e-5)
