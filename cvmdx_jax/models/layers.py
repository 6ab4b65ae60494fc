"""Building blocks of the 1-D U-Net: timestep embedding, FiLM residual block,
self-attention, resampling. Channels-last: (B, L, C).

Conventions of the official cVMDx U-Net: GroupNorm epsilon 1e-5 and a stride-2
downsampling convolution with padding 1 on both sides (output i sees inputs
2i - 1, 2i, 2i + 1).
"""

import math

import jax
import jax.numpy as jnp
from flax import nnx

from cvmdx_jax.models import winograd
from cvmdx_jax.models.group_norm import GroupNorm


def timestep_embedding(t, dim: int, max_period: float = 10000.0):
  """Sinusoidal embedding of integer timesteps t (B,) -> (B, dim)."""
  half = dim // 2
  freqs = jnp.exp(-math.log(max_period) * jnp.arange(half, dtype=jnp.float32) / half)
  args = jnp.asarray(t, jnp.float32)[:, None] * freqs[None]
  return jnp.concatenate([jnp.cos(args), jnp.sin(args)], axis=-1)


GROUPNORM_EPSILON = 1e-5  # the official code's (PyTorch's) GroupNorm epsilon


def group_norm(channels: int, groups: int) -> GroupNorm:
  return GroupNorm(channels, min(groups, channels), GROUPNORM_EPSILON)


def conv_same3(conv: nnx.Conv, x):
  """A width-3, stride-1 "SAME" `nnx.Conv` (its parameters) applied by `winograd.conv3`."""
  return winograd.conv3(x, conv.kernel[...]) + conv.bias[...]


class ResBlock(nnx.Module):
  """GroupNorm-SiLU-Conv, FiLM (scale, shift) from the embedding, GroupNorm-SiLU-
  Dropout-Conv (zero-initialised), plus a 1x1 skip where channels change."""

  def __init__(
      self, in_ch: int, out_ch: int, emb_dim: int, groups: int, dropout: float, *, rngs: nnx.Rngs
  ):
    self.norm1 = group_norm(in_ch, groups)
    self.conv1 = nnx.Conv(in_ch, out_ch, kernel_size=(3,), rngs=rngs)
    self.film = nnx.Linear(emb_dim, 2 * out_ch, rngs=rngs)
    self.norm2 = group_norm(out_ch, groups)
    self.dropout = nnx.Dropout(dropout)
    self.conv2 = nnx.Conv(
        out_ch, out_ch, kernel_size=(3,), kernel_init=nnx.initializers.zeros, rngs=rngs
    )
    self.skip = nnx.Conv(in_ch, out_ch, kernel_size=(1,), rngs=rngs) if in_ch != out_ch else None

  def prepare(self):
    """For inference: both width-3 kernels `winograd.prepare_kernel`ed (idempotent)."""
    for conv in (self.conv1, self.conv2):
      conv.kernel.set_value(winograd.prepare_kernel(conv.kernel[...]))

  def __call__(self, x, emb, dropout_key=None):
    h = conv_same3(self.conv1, self.norm1.silu(x))
    scale, shift = jnp.split(self.film(jax.nn.silu(emb)), 2, axis=-1)  # (B, C) each
    h = self.norm2.silu(h, 1.0 + scale, shift)
    if dropout_key is not None:
      h = self.dropout(h, deterministic=False, rngs=dropout_key)
    h = conv_same3(self.conv2, h)
    return h + (x if self.skip is None else self.skip(x))


class ResAttnBlock(nnx.Module):
  """A residual block, followed by self-attention when `num_heads` > 0."""

  def __init__(
      self,
      in_ch: int,
      out_ch: int,
      emb_dim: int,
      groups: int,
      dropout: float,
      num_heads: int,
      *,
      rngs: nnx.Rngs,
  ):
    self.res = ResBlock(in_ch, out_ch, emb_dim, groups, dropout, rngs=rngs)
    self.attn = AttentionBlock(out_ch, num_heads, groups, rngs=rngs) if num_heads else None

  def __call__(self, x, emb, dropout_key=None):
    h = self.res(x, emb, dropout_key)
    return h if self.attn is None else self.attn(h)


class AttentionBlock(nnx.Module):
  """Pre-norm multi-head self-attention over the sequence axis, residual."""

  def __init__(self, channels: int, num_heads: int, groups: int, *, rngs: nnx.Rngs):
    self.norm = group_norm(channels, groups)
    self.attn = nnx.MultiHeadAttention(
        num_heads=num_heads, in_features=channels, decode=False, rngs=rngs
    )

  def __call__(self, x):
    return x + self.attn(self.norm(x))


class Downsample(nnx.Module):
  """Strided convolution with padding 1 each side, L -> L / 2 (L even): output i is
  centred on input 2i."""

  def __init__(self, channels: int, *, rngs: nnx.Rngs):
    self.conv = nnx.Conv(
        channels, channels, kernel_size=(3,), strides=(2,), padding=((1, 1),), rngs=rngs
    )

  def __call__(self, x):
    return self.conv(x)


class Upsample(nnx.Module):
  """Nearest-neighbour repeat then a width-3 convolution, L -> 2 L.

  Computed without the repeat: with kernel taps (w0, w1, w2), output 2i is
  w0 x[i-1] + (w1 + w2) x[i] and output 2i+1 is (w0 + w1) x[i] + w2 x[i+1]. One width-3
  convolution of x with both phases' kernels side by side, (w0, w1 + w2, 0) and
  (0, w0 + w1, w2), gives (B, L, 2 C), which is the interleaved (B, 2 L, C) in memory
  (XLA:CPU: a width-2 convolution is ~100x slower, and the repeated sequence costs a
  copy). Parameters are those of the convolution of the repeated sequence (`conv`, as
  in the official code).
  """

  def __init__(self, channels: int, *, rngs: nnx.Rngs):
    self.conv = nnx.Conv(channels, channels, kernel_size=(3,), rngs=rngs)

  def phase_kernel(self):
    """(3, C, 2 C): both phases' kernels side by side."""
    w0, w1, w2 = self.conv.kernel[...]
    zero = jnp.zeros_like(w0)
    return jnp.concatenate(
        [jnp.stack([w0, w1 + w2, zero]), jnp.stack([zero, w0 + w1, w2])], -1  # output 2i
    )  # output 2i + 1

  def prepare(self):
    """For inference: `conv.kernel` becomes the prepared phase kernel where that is
    transformed (`winograd.prepare_kernel`), so no call rebuilds it; idempotent."""
    if winograd.is_transformed(self.conv.kernel[...]):
      return
    kernel = winograd.prepare_kernel(self.phase_kernel())
    if winograd.is_transformed(kernel):
      self.conv.kernel.set_value(kernel)

  def __call__(self, x):
    kernel = self.conv.kernel[...]
    y = winograd.conv3(x, kernel if winograd.is_transformed(kernel) else self.phase_kernel())
    b, length, channels = x.shape
    return y.reshape(b, 2 * length, channels) + self.conv.bias[...]
