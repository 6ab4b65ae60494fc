"""GroupNorm over channels-last sequences (B, L, C) with a hand-written backward pass.

Same function as `flax.nnx.GroupNorm` (statistics per example and group of C / G
channels over the whole sequence, the fast variance E[x^2] - E[x]^2, then a per-channel
scale and bias), written for XLA:CPU: the per-(example, channel) coefficients are
computed once as (B, C) arrays, so the large loops over (B, L, C) are one multiply-add
each (forward: y = x a + b; backward: dx = A dy + B x + C). With autodiff through
`nnx.GroupNorm`, XLA fused the (B, G) -> (B, C) expansion into every large loop, which
made them index-bound. `group_norm_silu` also takes the SiLU (and a FiLM modulation
before it) into the same loops: one pass forward, the sigmoid recomputed backward instead
of stored. With both and the phase-split upsampling (`layers.Upsample`) the reference-size
training step went from 3.75 to 3.12 s on 2 CPU cores (docs/log, "Training step:
GroupNorm and upsampling").

The (B, G) -> (B, C) expansion is a product with a 0/1 matrix: XLA:CPU keeps a dot out of
the loop fusions (an `optimization_barrier` does not survive its pipeline).

All of this is the fast path of the performance option `group_norm_backward`
(`models.performance`); `GroupNorm` takes it as the option says: "auto" (default) on the
CPU backend only, chosen per platform when the function is lowered; "on" everywhere;
"off" never, where `plain_group_norm` / `plain_group_norm_silu` (the reshape to groups of
`nnx.GroupNorm`, autodiff) are traced instead: XLA's plain path, what other backends get.
Set by `CVMDX_GROUP_NORM_BACKWARD=auto|on|off` or `performance.use`. `group_norm` and
`group_norm_silu` themselves are always the fast path.
"""

import functools

import jax
import jax.numpy as jnp
from flax import nnx

from cvmdx_jax.errors import UserError
from cvmdx_jax.models import performance


def _expand(v, group_size: int):
  """(B, G) -> (B, G * group_size), each group's value repeated over its channels."""
  ones = jnp.repeat(jnp.eye(v.shape[1], dtype=v.dtype), group_size, axis=1)
  return jnp.dot(v, ones, precision=jax.lax.Precision.HIGHEST)


def _group_sum(v, groups: int):
  """(B, C) -> (B, G): sums over each group's channels."""
  return v.reshape(v.shape[0], groups, -1).sum(-1)


def _check_groups(channels: int, groups: int, who: str) -> None:
  if channels % groups:
    raise UserError(f"{who}: {channels} channels are not divisible by {groups} groups")


def _statistics(x, groups: int, epsilon: float):
  """Per-example, per-group mean and 1 / std of x (B, L, C) -> (B, G) each."""
  length, channels = x.shape[1:]
  _check_groups(channels, groups, "group_norm")
  n = length * (channels // groups)
  mean = _group_sum(jnp.sum(x, axis=1), groups) / n
  var = jnp.maximum(_group_sum(jnp.sum(x * x, axis=1), groups) / n - mean * mean, 0.0)
  return mean, jax.lax.rsqrt(var + epsilon)


def _coefficients(scale, bias, mean, rstd):
  """(a, shift), each (B, C), with GroupNorm(x) = x a + shift."""
  gs = scale.shape[0] // mean.shape[1]
  a = _expand(rstd, gs) * scale
  return a, bias - _expand(mean, gs) * a


def _backward_coefficients(s1, s2, length: int, scale, mean, rstd):
  """Gradients of GroupNorm from s1 = sum_L dn and s2 = sum_L dn x, each (B, C), where
  dn (B, L, C) is the cotangent of its output: (d_scale, d_bias, k_dn, k_x, k_1) with
  dx = dn k_dn + x k_x + k_1 (the k's (B, C))."""
  groups, gs = mean.shape[1], scale.shape[0] // mean.shape[1]
  n = length * gs
  mean_c, rstd_c = _expand(mean, gs), _expand(rstd, gs)
  d_scale = jnp.sum(rstd_c * (s2 - mean_c * s1), axis=0)
  d_bias = jnp.sum(s1, axis=0)
  # with g = dn scale and xhat = (x - mean) rstd, per group:
  # dx = rstd (g - mean(g) - xhat mean(g xhat))
  m_g = _group_sum(scale * s1, groups) / n
  m_gxhat = rstd * (_group_sum(scale * s2, groups) / n - mean * m_g)
  k_x = _expand(-rstd * rstd * m_gxhat, gs)
  k_1 = _expand(rstd * rstd * mean * m_gxhat - rstd * m_g, gs)
  return d_scale, d_bias, rstd_c * scale, k_x, k_1


def _bcast(v):
  return v[:, None, :]


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def group_norm(x, scale, bias, groups: int, epsilon: float):
  """GroupNorm of x (B, L, C) with `groups` groups; scale, bias (C,) -> (B, L, C)."""
  return _group_norm_forward(x, scale, bias, groups, epsilon)[0]


def _group_norm_forward(x, scale, bias, groups, epsilon):
  mean, rstd = _statistics(x, groups, epsilon)
  a, shift = _coefficients(scale, bias, mean, rstd)
  return x * _bcast(a) + _bcast(shift), (x, scale, mean, rstd)


def _group_norm_backward(groups, epsilon, residuals, dy):
  del groups, epsilon  # in mean and rstd already
  x, scale, mean, rstd = residuals
  d_scale, d_bias, k_dn, k_x, k_1 = _backward_coefficients(
      jnp.sum(dy, axis=1), jnp.sum(dy * x, axis=1), x.shape[1], scale, mean, rstd
  )
  return dy * _bcast(k_dn) + x * _bcast(k_x) + _bcast(k_1), d_scale, d_bias


group_norm.defvjp(_group_norm_forward, _group_norm_backward)


@functools.partial(jax.custom_vjp, nondiff_argnums=(5, 6))
def group_norm_silu(x, scale, bias, mod_scale, mod_shift, groups: int, epsilon: float):
  """silu(group_norm(x) m + c) with a per-example modulation m, c (B, C) (FiLM; ones and
  zeros for none) -> (B, L, C)."""
  return _group_norm_silu_forward(x, scale, bias, mod_scale, mod_shift, groups, epsilon)[0]


def _modulated(x, a, shift, mod_scale, mod_shift):
  """group_norm(x) m + c from GroupNorm's coefficients (a, shift) -> (B, L, C)."""
  return x * _bcast(a * mod_scale) + _bcast(shift * mod_scale + mod_shift)


def _group_norm_silu_forward(x, scale, bias, mod_scale, mod_shift, groups, epsilon):
  mean, rstd = _statistics(x, groups, epsilon)
  a, shift = _coefficients(scale, bias, mean, rstd)
  return (
      jax.nn.silu(_modulated(x, a, shift, mod_scale, mod_shift)),
      (x, scale, mod_scale, mod_shift, mean, rstd, a, shift),
  )


def _group_norm_silu_backward(groups, epsilon, residuals, dy):
  del groups, epsilon
  x, scale, mod_scale, mod_shift, mean, rstd, a, shift = residuals
  u = _modulated(x, a, shift, mod_scale, mod_shift)
  sig = jax.nn.sigmoid(u)
  du = dy * sig * (1.0 + u * (1.0 - sig))  # (B, L, C)
  r1, r2 = jnp.sum(du, axis=1), jnp.sum(du * x, axis=1)  # (B, C)
  d_mod_scale, d_mod_shift = a * r2 + shift * r1, r1  # sum_L du xhat', du
  # the GroupNorm output's cotangent is dn = du m
  d_scale, d_bias, k_dn, k_x, k_1 = _backward_coefficients(
      mod_scale * r1, mod_scale * r2, x.shape[1], scale, mean, rstd
  )
  dx = du * _bcast(k_dn * mod_scale) + x * _bcast(k_x) + _bcast(k_1)
  return dx, d_scale, d_bias, d_mod_scale, d_mod_shift


group_norm_silu.defvjp(_group_norm_silu_forward, _group_norm_silu_backward)


def plain_group_norm(x, scale, bias, groups: int, epsilon: float):
  """`group_norm` as `flax.nnx.GroupNorm` writes it (reshape to groups, the same fast
  variance), for autodiff: XLA's plain path (module docstring)."""
  b, length, channels = x.shape
  _check_groups(channels, groups, "group_norm")
  xg = x.reshape(b, length, groups, channels // groups)
  mean = jnp.mean(xg, axis=(1, 3), keepdims=True)
  var = jnp.maximum(jnp.mean(xg * xg, axis=(1, 3), keepdims=True) - mean * mean, 0.0)
  return ((xg - mean) * jax.lax.rsqrt(var + epsilon)).reshape(x.shape) * scale + bias


def plain_group_norm_silu(x, scale, bias, mod_scale, mod_shift, groups: int, epsilon: float):
  """`group_norm_silu` from `plain_group_norm`, for autodiff."""
  normed = plain_group_norm(x, scale, bias, groups, epsilon)
  return jax.nn.silu(normed * _bcast(mod_scale) + _bcast(mod_shift))


def _select(fast, plain, groups: int, epsilon: float, *args):
  """fast or plain (each taking `groups, epsilon` last) on args, as the
  `group_norm_backward` performance option says."""
  return performance.select(
      "group_norm_backward",
      lambda *a: fast(*a, groups, epsilon),
      lambda *a: plain(*a, groups, epsilon),
      *args,
  )


class GroupNorm(nnx.Module):
  """`group_norm` with learned `scale` (ones) and `bias` (zeros), the parameter names of
  `nnx.GroupNorm`, over inputs (B, L, C); `silu` gives silu(norm(x) m + c)."""

  def __init__(self, num_features: int, num_groups: int, epsilon: float):
    _check_groups(num_features, num_groups, "GroupNorm")
    self.num_groups, self.epsilon = num_groups, epsilon
    self.scale = nnx.Param(jnp.ones((num_features,)))
    self.bias = nnx.Param(jnp.zeros((num_features,)))

  def __call__(self, x):
    return _select(
        group_norm,
        plain_group_norm,
        self.num_groups,
        self.epsilon,
        x,
        self.scale[...],
        self.bias[...],
    )

  def silu(self, x, mod_scale=None, mod_shift=None):
    """silu(self(x) mod_scale + mod_shift); mod_* (B, C), default ones / zeros."""
    b, c = x.shape[0], x.shape[-1]
    mod_scale = jnp.ones((b, c), x.dtype) if mod_scale is None else mod_scale
    mod_shift = jnp.zeros((b, c), x.dtype) if mod_shift is None else mod_shift
    return _select(
        group_norm_silu,
        plain_group_norm_silu,
        self.num_groups,
        self.epsilon,
        x,
        self.scale[...],
        self.bias[...],
        mod_scale,
        mod_shift,
    )
