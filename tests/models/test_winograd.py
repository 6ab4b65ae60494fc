"""Winograd F(4, 3) convolution against XLA's direct convolution and a hand-worked case."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax.models import performance, winograd


def _direct(x, kernel):
  return jax.lax.conv_general_dilated(
      x, kernel, (1,), "SAME", dimension_numbers=("NWC", "WIO", "NWC")
  )


def test_hand_worked_sequence():
  # one channel, taps (1, 2, 3): y_i = x_{i-1} + 2 x_i + 3 x_{i+1}, zero outside
  x = jnp.arange(1.0, 9.0).reshape(1, 8, 1)
  kernel = jnp.array([1.0, 2.0, 3.0]).reshape(3, 1, 1)
  expected = [
      0 + 2 + 6,
      1 + 4 + 9,
      2 + 6 + 12,
      3 + 8 + 15,
      4 + 10 + 18,
      5 + 12 + 21,
      6 + 14 + 24,
      7 + 16 + 0,
  ]
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


@pytest.mark.parametrize("length", [1, 6, 7, 18])
def test_any_length_with_raw_or_transformed_taps(length):
  # lengths that are not a multiple of 4 are zero-padded and cropped: the "SAME" zeros
  x = jax.random.normal(jax.random.key(3), (2, length, 5))
  kernel = jax.random.normal(jax.random.key(4), (3, 5, 4))
  transformed = winograd.transform_kernel(kernel)
  assert transformed.shape == (6, 5, 4) and winograd.is_transformed(transformed)
  for taps in (kernel, transformed):
    np.testing.assert_allclose(
        winograd.winograd_conv(x, taps),
        _direct(x, kernel),
        atol=1e-5 * float(jnp.max(jnp.abs(_direct(x, kernel)))),
    )


def test_transform_is_g_times_the_taps():
  # V = G g with the rows of F(4, 3)'s G (Lavin & Gray 2016): (1/4, 0, 0),
  # (-1/6, -1/6, -1/6), (-1/6, 1/6, -1/6), (1/24, 1/12, 1/6), (1/24, -1/12, 1/6), (0, 0, 1);
  # one channel with taps (1, 2, 3) worked by hand
  got = winograd.transform_kernel(jnp.array([1.0, 2.0, 3.0]).reshape(3, 1, 1))[:, 0, 0]
  np.testing.assert_allclose(
      got, [1 / 4, -1, -1 / 3, 1 / 24 + 2 / 12 + 3 / 6, 1 / 24 - 2 / 12 + 3 / 6, 3], rtol=1e-6
  )


def test_conv3_takes_a_transformed_kernel_at_any_length():
  big = winograd.MIN_CHANNELS
  x = jax.random.normal(jax.random.key(1), (2, 18, big))
  kernel = jax.random.normal(jax.random.key(2), (3, big, big)) / 20
  with performance.use(performance.PerformanceOptions(winograd="off")):
    # a prepared kernel is in the transformed domain: only F(4, 3) can apply it
    jaxpr = str(jax.make_jaxpr(winograd.conv3)(x, winograd.transform_kernel(kernel)))
    out = winograd.conv3(x, winograd.transform_kernel(kernel))
  assert "conv_general_dilated" not in jaxpr
  np.testing.assert_allclose(out, _direct(x, kernel), atol=1e-5 * float(jnp.abs(out).max()))


@pytest.mark.parametrize("option, transformed", [("on", True), ("off", False)])
def test_prepare_kernel_by_channels_and_option(option, transformed):
  big = winograd.MIN_CHANNELS
  kernel = jax.random.normal(jax.random.key(5), (3, big, big))
  small = jax.random.normal(jax.random.key(6), (3, big - 1, big))
  with performance.use(performance.PerformanceOptions(winograd=option)):
    prepared = winograd.prepare_kernel(kernel)
    assert winograd.is_transformed(prepared) == transformed
    assert winograd.prepare_kernel(small) is small  # too few channels: as is
    assert winograd.prepare_kernel(prepared) is prepared  # idempotent
  if transformed:
    np.testing.assert_allclose(prepared, winograd.transform_kernel(kernel), rtol=1e-6)
