"""Winograd F(4, 3) convolution against XLA's direct convolution and a hand-worked case."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax.models import performance, winograd


def _direct(x, kernel):
  return jax.lax.conv_general_dilated(x, kernel, (1,), "SAME",
                                      dimension_numbers=("NWC", "WIO", "NWC"))


def test_hand_worked_sequence():
  # one channel, taps (1, 2, 3): y_i = x_{i-1} + 2 x_i + 3 x_{i+1}, zero outside
  x = jnp.arange(1.0, 9.0).reshape(1, 8, 1)
  kernel = jnp.array([1.0, 2.0, 3.0]).reshape(3, 1, 1)
  expected = [0 + 2 + 6, 1 + 4 + 9, 2 + 6 + 12, 3 + 8 + 15, 4 + 10 + 18, 5 + 12 + 21,
              6 + 14 + 24, 7 + 16 + 0]
  np.testing.assert_allclose(winograd.winograd_conv(x, kernel)[0, :, 0], expected, rtol=1e-6)


@pytest.mark.parametrize("shape", [(2, 4, 3, 5), (3, 16, 8, 7), (2, 32, 130, 129)])
def test_matches_direct_convolution_and_its_gradients(shape):
  b, length, c, o = shape
  kx, kw, ky = jax.random.split(jax.random.key(0), 3)
  x = jax.random.normal(kx, (b, length, c))
  kernel = jax.random.normal(kw, (3, c, o)) / np.sqrt(3 * c)
  dy = jax.random.normal(ky, (b, length, o))
  out, vjp = jax.vjp(winograd.winograd_conv, x, kernel)
  ref, ref_vjp = jax.vjp(_direct, x, kernel)
  np.testing.assert_allclose(out, ref, atol=2e-5 * float(jnp.max(jnp.abs(ref))))
  for got, want in zip(vjp(dy), ref_vjp(dy)):
    np.testing.assert_allclose(got, want, atol=2e-5 * float(jnp.max(jnp.abs(want))))


def test_conv3_chooses_by_channels_and_length():
  def uses_winograd(shape, out_channels):
    x = jnp.zeros(shape)
    with performance.use(performance.PerformanceOptions(winograd="on")):
      jaxpr = jax.make_jaxpr(winograd.conv3)(x, jnp.zeros((3, shape[-1], out_channels)))
    return "conv_general_dilated" not in str(jaxpr)
  big = winograd.MIN_CHANNELS
  assert uses_winograd((2, 16, big), big)
  assert not uses_winograd((2, 16, big - 1), big)  # too few input channels
  assert not uses_winograd((2, 16, big), 2)  # too few output channels
  assert not uses_winograd((2, 18, big), big)  # length not a multiple of 4
  x = jax.random.normal(jax.random.key(1), (2, 18, big))
  kernel = jax.random.normal(jax.random.key(2), (3, big, big)) / 20
  np.testing.assert_allclose(winograd.conv3(x, kernel), _direct(x, kernel), rtol=1e-6)


def test_rejects_a_length_it_cannot_tile():
  with pytest.raises(ValueError, match="divisible by 4"):
    winograd.winograd_conv(jnp.zeros((1, 6, 2)), jnp.zeros((3, 2, 2)))
