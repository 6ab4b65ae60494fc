"""1-D U-Net denoiser v_theta(x_t, t, q) over the (B, 125, 2) control sequence.

Reference defaults (cVMDx): 128 base channels, multipliers (1, 2, 3, 4), one
residual block per level, 4-head self-attention at the two coarsest levels,
FiLM conditioning from timestep embedding + learned token embedding with one
extra null token (index `num_tokens`) for classifier-free guidance. As in the
official cVMDx code, the sequence is zero-padded centred from 125 to 128 (1 step
left, 2 right) and the same centred window [1:126] is cropped back; the stride-2
downsampling pads 1 each side and GroupNorm uses epsilon 1e-5 (`layers`), so
official checkpoints give the official outputs (`official_import`).
Beyond the paper, an optional conditioning vector c (B, cond_dim) (ego-motion
features, `cvmdx_jax.ego_motion`) adds its MLP embedding to the same FiLM
embedding; the null token drops only q.

Functional use: `graphdef, params = init_unet(config, key)`, then
`apply_unet(graphdef, params, x_t, t, q)` (or `..., cond=c` when cond_dim > 0) inside
`jax.jit`.
"""

import functools

import jax
import jax.numpy as jnp
from flax import nnx

from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.models import functional
from cvmdx_jax.models.layers import (
    Downsample,
    ResAttnBlock,
    ResBlock,
    Upsample,
    group_norm,
    timestep_embedding,
)


class UNet1D(nnx.Module):
  """`model(x_t (B, L, C), t (B,) int, q (B,) int[, cond (B, cond_dim)]) -> v (B, L, C)`."""

  def __init__(self, config: UNetConfig, *, rngs: nnx.Rngs):
    self.config = config
    ch, levels = config.base_channels, len(config.channel_mult)
    emb_dim = config.emb_mult * ch

    def block(level, in_ch, out_ch):
      heads = config.num_heads if level in config.attention_levels else 0
      return ResAttnBlock(in_ch, out_ch, emb_dim, config.groups, config.dropout, heads, rngs=rngs)

    self.time_mlp1 = nnx.Linear(ch, emb_dim, rngs=rngs)
    self.time_mlp2 = nnx.Linear(emb_dim, emb_dim, rngs=rngs)
    self.token_embed = nnx.Embed(config.num_tokens + 1, emb_dim, rngs=rngs)
    if config.cond_dim:
      # cond_mlp1 -> SiLU -> (cond_mlp_hidden[i] -> SiLU)* -> cond_mlp2 (names of the
      # one-hidden-layer MLP kept, so that its checkpoints load)
      widths = config.cond_widths
      self.cond_mlp1 = nnx.Linear(config.cond_dim, widths[0], rngs=rngs)
      if len(widths) > 1:
        self.cond_mlp_hidden = nnx.List(
            [nnx.Linear(a, b, rngs=rngs) for a, b in zip(widths, widths[1:])]
        )
      self.cond_mlp2 = nnx.Linear(widths[-1], emb_dim, rngs=rngs)
    self.conv_in = nnx.Conv(config.channels, ch, kernel_size=(3,), rngs=rngs)

    skip_channels, down_blocks, down_samples, cur = [ch], [], [], ch
    for level, mult in enumerate(config.channel_mult):
      for _ in range(config.num_res_blocks):
        down_blocks.append(block(level, cur, mult * ch))
        cur = mult * ch
        skip_channels.append(cur)
      if level < levels - 1:
        down_samples.append(Downsample(cur, rngs=rngs))
        skip_channels.append(cur)
    self.down_blocks, self.down_samples = nnx.List(down_blocks), nnx.List(down_samples)
    # middle: residual + attention, then residual
    self.mid = nnx.List(
        [
            ResAttnBlock(
                cur, cur, emb_dim, config.groups, config.dropout, config.num_heads, rngs=rngs
            ),
            ResAttnBlock(cur, cur, emb_dim, config.groups, config.dropout, 0, rngs=rngs),
        ]
    )

    up_blocks, up_samples = [], []
    for level, mult in reversed(list(enumerate(config.channel_mult))):
      for _ in range(config.num_res_blocks + 1):
        up_blocks.append(block(level, cur + skip_channels.pop(), mult * ch))
        cur = mult * ch
      if level > 0:
        up_samples.append(Upsample(cur, rngs=rngs))
    self.up_blocks, self.up_samples = nnx.List(up_blocks), nnx.List(up_samples)
    self.norm_out = group_norm(cur, config.groups)
    self.conv_out = nnx.Conv(
        cur, config.channels, kernel_size=(3,), kernel_init=nnx.initializers.zeros, rngs=rngs
    )
    if config.num_intents:  # last, so that every other parameter draws as without it
      widths = (config.intent_features,) + config.cond_widths + (config.num_intents,)
      self.intent_mlp = nnx.List([nnx.Linear(a, b, rngs=rngs) for a, b in zip(widths, widths[1:])])

  def embedding(self, t, q, cond=None):
    """The FiLM embedding (B, emb_mult * base_channels): the timestep's MLP + the token's
    embedding (+ the conditioning vector's MLP where cond_dim > 0)."""
    cfg = self.config
    emb = self.time_mlp2(jax.nn.silu(self.time_mlp1(timestep_embedding(t, cfg.base_channels))))
    emb = emb + self.token_embed(q)
    if cfg.cond_dim:
      h = jax.nn.silu(self.cond_mlp1(cond))
      for layer in self.cond_mlp_hidden if len(cfg.cond_widths) > 1 else ():
        h = jax.nn.silu(layer(h))
      emb = emb + self.cond_mlp2(h)
    return emb

  def intent_logits(self, features):
    """Intent classifier logits (B, num_intents) for features (B, intent_features)."""
    h = features
    for layer in self.intent_mlp[:-1]:
      h = jax.nn.silu(layer(h))
    return self.intent_mlp[-1](h)

  def __call__(self, x_t, t, q, dropout_key=None, cond=None):
    cfg = self.config
    if (cond is None) != (cfg.cond_dim == 0):
      raise ValueError(
          f"UNet1D: cond_dim={cfg.cond_dim} but cond is "
          f"{None if cond is None else jnp.shape(cond)}"
      )
    keys = iter(
        jax.random.split(dropout_key, len(self.down_blocks) + len(self.up_blocks) + 2)
        if dropout_key is not None
        else []
    )
    key = lambda: next(keys, None)
    emb = self.embedding(t, q, cond)
    length = x_t.shape[1]
    left = (cfg.padded_length - length) // 2
    h = self.conv_in(jnp.pad(x_t, ((0, 0), (left, cfg.padded_length - length - left), (0, 0))))
    skips, blocks = [h], iter(self.down_blocks)
    for level in range(len(cfg.channel_mult)):
      for _ in range(cfg.num_res_blocks):
        h = next(blocks)(h, emb, key())
        skips.append(h)
      if level < len(self.down_samples):
        h = self.down_samples[level](h)
        skips.append(h)
    for mid in self.mid:
      h = mid(h, emb, key())
    blocks, samples = iter(self.up_blocks), iter(self.up_samples)
    for level in reversed(range(len(cfg.channel_mult))):
      for _ in range(cfg.num_res_blocks + 1):
        h = next(blocks)(jnp.concatenate([h, skips.pop()], axis=-1), emb, key())
      if level > 0:
        h = next(samples)(h)
    out = self.conv_out(self.norm_out.silu(h))
    return out[:, left : left + length]


def init_unet(config: UNetConfig, key: jax.Array):
  """Builds the model; returns (graphdef, params), params a pure dict of arrays."""
  return functional.init(lambda rngs: UNet1D(config, rngs=rngs), key)


def make_graphdef(config: UNetConfig):
  """The graph definition alone (no parameters are allocated)."""
  return functional.make_graphdef(UNet1D, config)


def abstract_params(config: UNetConfig) -> dict:
  """The parameters' shapes and dtypes (`jax.ShapeDtypeStruct`s; nothing is allocated)."""
  return functional.abstract_params(UNet1D, config)


def apply_unet(graphdef, params, x_t, t, q, dropout_key=None, cond=None):
  """Functional forward pass: v (B, L, C); cond (B, cond_dim) iff cond_dim > 0."""
  return nnx.merge(graphdef, params)(x_t, t, q, dropout_key, cond)


def apply_intent(graphdef, params, features):
  """Functional intent classifier: logits (B, num_intents) for features (B,
  intent_features)."""
  return nnx.merge(graphdef, params).intent_logits(features)


def count_params(params) -> int:
  return sum(x.size for x in jax.tree.leaves(params))


@functools.partial(jax.jit, static_argnums=0)
def prepare_params(graphdef, params) -> dict:
  """`params` for inference on this backend: the width-3 kernels that `winograd.conv3` runs
  by F(4, 3) transformed once (`winograd.prepare_kernel`), so that no forward pass repeats
  the transform (at the reference size ~12 ms a pass on 2 CPU cores, BUILD_NOTES.md);
  idempotent. Jitted, the transform rounds as inside the forward pass: `apply_unet` gives the
  same outputs bit for bit with either. Not for training or checkpoints: the prepared
  kernels are another parametrisation."""
  model = nnx.merge(graphdef, params)
  for _, module in nnx.iter_graph(model):
    if isinstance(module, (ResBlock, Upsample)):
      module.prepare()
  return nnx.to_pure_dict(nnx.split(model, nnx.Param)[1])
