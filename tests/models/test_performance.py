"""The per-backend performance options (`cvmdx_jax.models.performance`): "auto" on CPU is
today's fast path bit for bit, "off" is XLA's plain path to float32 rounding, each value
traces the path it names, and a bad value is refused by name."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.models import performance, unet1d, winograd
from cvmdx_jax.models.group_norm import GroupNorm
from cvmdx_jax.models.performance import PerformanceOptions

ON, OFF = PerformanceOptions("on", "on"), PerformanceOptions("off", "off")


def _wide_unet(channel_mult: tuple[int, ...]):
  """(graphdef, params) of a U-Net of 128 channels (Winograd taken) on sequences of 6 steps,
  its zero-initialised output convolutions made non-zero so that every gradient flows."""
  config = UNetConfig(
      num_tokens=4,
      base_channels=128,
      channel_mult=channel_mult,
      attention_levels=(),
      num_heads=1,
      length=6,
      padded_length=8,
  )
  graphdef, params = unet1d.init_unet(config, jax.random.key(0))
  params = jax.tree.map(lambda p: p + 0.05 * jax.random.normal(jax.random.key(1), p.shape), params)
  return graphdef, params


def _forward_and_gradient(options):
  """A U-Net with 128 channels (Winograd taken) on a short sequence: its output and the
  gradient of a non-linear read-out over all parameters, in one jitted call."""
  graphdef, params = _wide_unet(channel_mult=(1,))
  keys = jax.random.split(jax.random.key(2), 2)
  x, weight = jax.random.normal(keys[0], (2, 6, 2)), jax.random.normal(keys[1], (2, 6, 2))
  forward = lambda p: unet1d.apply_unet(graphdef, p, x, jnp.array([3, 500]), jnp.array([0, 4]))
  loss = lambda p: jnp.sum(weight * jnp.sin(forward(p)))
  with performance.use(options):
    return jax.jit(lambda p: (forward(p), jax.grad(loss)(p)))(params)


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="what auto means on CPU")
def test_auto_on_cpu_is_the_fast_path_bit_for_bit_and_off_the_plain_one_to_rounding():
  out_on, grad_on = _forward_and_gradient(ON)
  out_auto, grad_auto = _forward_and_gradient(PerformanceOptions())
  assert np.array_equal(out_auto, out_on)
  assert jax.tree.all(jax.tree.map(np.array_equal, grad_auto, grad_on))
  out_off, grad_off = _forward_and_gradient(OFF)
  np.testing.assert_allclose(out_off, out_on, atol=2e-5 * float(jnp.abs(out_on).max()))
  scale = max(float(jnp.abs(g).max()) for g in jax.tree.leaves(grad_on))
  for got, want in zip(jax.tree.leaves(grad_off), jax.tree.leaves(grad_on)):
    np.testing.assert_allclose(got, want, atol=2e-5 * scale)


def _primitives(fn, *args) -> str:
  return str(jax.make_jaxpr(fn)(*args))


@pytest.mark.parametrize(
    "value, fast, plain", [("on", True, False), ("off", False, True), ("auto", True, True)]
)
def test_each_value_traces_the_paths_it_names(value, fast, plain):
  x, kernel = jnp.zeros((2, 8, 128)), jnp.zeros((3, 128, 128))
  norm = GroupNorm(128, 32, 1e-5)
  with performance.use(PerformanceOptions(value, value)):
    conv = _primitives(winograd.conv3, x, kernel)
    # Winograd's transformed GEMMs are the only dot_general of conv3
    assert ("dot_general" in conv, "conv_general_dilated" in conv) == (fast, plain)
    for fn in (norm, norm.silu):
      jaxpr = _primitives(fn, x)
      assert "custom_vjp_call" in jaxpr if fast else "custom_vjp_call" not in jaxpr
    # "auto" stages both out behind the platform, resolved when lowered
    assert ("platform_index" in conv) == (value == "auto")
    # below 128 channels it is XLA's convolution whatever the option
    assert "dot_general" not in _primitives(winograd.conv3, x[..., :64], kernel[:, :64, :64])


def test_resolved_per_platform_and_described():
  auto = PerformanceOptions()
  assert auto.resolved("cpu") == {"winograd": True, "group_norm_backward": True}
  assert auto.resolved("gpu") == {"winograd": False, "group_norm_backward": False}
  assert PerformanceOptions("on", "off").resolved("gpu") == {
      "winograd": True,
      "group_norm_backward": False,
  }
  assert auto.describe("gpu") == "winograd=auto (off), group_norm_backward=auto (off)"


def test_environment_values_and_bad_values_named():
  assert performance.from_environment({}) == PerformanceOptions()
  assert performance.from_environment(
      {"CVMDX_WINOGRAD": "off", "CVMDX_GROUP_NORM_BACKWARD": ""}
  ) == PerformanceOptions("off")
  with pytest.raises(
      ValueError, match="CVMDX_GROUP_NORM_BACKWARD='yes': expected one of " "auto, on, off"
  ):
    performance.from_environment({"CVMDX_GROUP_NORM_BACKWARD": "yes"})
  with pytest.raises(ValueError, match="winograd='fast'"):
    PerformanceOptions(winograd="fast")


def test_use_sets_the_options_for_a_block_and_retraces_jitted_functions():
  traced = []

  @jax.jit
  def conv(x, kernel):
    traced.append(performance.current().winograd)
    return winograd.conv3(x, kernel)

  x, kernel = jnp.ones((1, 4, 128)), jnp.ones((3, 128, 128))
  outside = performance.current()
  with performance.use(ON):
    conv(x, kernel)
    with performance.use(OFF):
      assert performance.current() == OFF
      conv(x, kernel)
    conv(x, kernel)
  assert performance.current() == outside
  assert traced == ["on", "off", "on"]


def _two_level_unet():
  """128 channels on two levels: residual blocks and an upsampling that take Winograd."""
  return _wide_unet(channel_mult=(1, 1))


def _transformed(params) -> int:
  return sum(winograd.is_transformed(p) for p in jax.tree.leaves(params) if p.ndim == 3)


@pytest.mark.parametrize("options, prepared", [(ON, 17), (OFF, 0)])
def test_prepared_params_forward_bit_for_bit_and_idempotent(options, prepared):
  graphdef, params = _two_level_unet()
  x = jax.random.normal(jax.random.key(2), (3, 6, 2))
  forward = jax.jit(
      lambda p: unet1d.apply_unet(graphdef, p, x, jnp.array([3, 500, 999]), jnp.array([0, 4, 1]))
  )
  with performance.use(options):
    once = unet1d.prepare_params(graphdef, params)
    twice = unet1d.prepare_params(graphdef, once)
    # the two width-3 kernels of 8 residual blocks (1 + 1 down, 2 mid, 2 + 2 up) and the
    # upsampling's phase kernel
    assert _transformed(once) == prepared
    assert jax.tree.all(jax.tree.map(np.array_equal, twice, once))
    assert np.array_equal(forward(once), forward(params))
  assert _transformed(params) == 0  # the checkpoint's parameters are left as they are
