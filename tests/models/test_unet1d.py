"""1-D U-Net: shapes, parameter count, null token, dropout, no retracing."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from cvmdx_jax.config.models import UNetConfig
from cvmdx_jax.models import layers, unet1d
from tests.models import tiny_nets

TINY = tiny_nets.unet_config(5, dropout=0.1, padded_length=128)


def _inputs(b=3):
  x = jax.random.normal(jax.random.key(0), (b, 125, 2))
  return x, jnp.arange(b) * 300, jnp.arange(b) % 5


def _params_count_by_hand(cfg):
  """Counts parameters of the documented architecture from its description."""
  ch, e = cfg.base_channels, cfg.emb_mult * cfg.base_channels
  conv = lambda i, o, k=3: k * i * o + o
  norm = lambda c: 2 * c
  res = lambda i, o: (
      norm(i)
      + conv(i, o)
      + e * 2 * o
      + 2 * o
      + norm(o)
      + conv(o, o)
      + (conv(i, o, 1) if i != o else 0)
  )
  attn = lambda c: norm(c) + 4 * (c * c + c)
  total = ch * e + e + e * e + e + (cfg.num_tokens + 1) * e + conv(cfg.channels, ch)
  skips, cur = [ch], ch
  levels = len(cfg.channel_mult)
  for lvl, m in enumerate(cfg.channel_mult):
    total += res(cur, m * ch) + (attn(m * ch) if lvl in cfg.attention_levels else 0)
    cur = m * ch
    skips.append(cur)
    if lvl < levels - 1:
      total += conv(cur, cur)
      skips.append(cur)
  total += 2 * res(cur, cur) + attn(cur)
  for lvl, m in reversed(list(enumerate(cfg.channel_mult))):
    for _ in range(2):
      total += res(cur + skips.pop(), m * ch) + (attn(m * ch) if lvl in cfg.attention_levels else 0)
      cur = m * ch
    if lvl > 0:
      total += conv(cur, cur)
  return total + norm(cur) + conv(cur, cfg.channels)


def test_shapes_and_param_count_tiny():
  g, p = unet1d.init_unet(TINY, jax.random.key(0))
  x, t, q = _inputs()
  out = unet1d.apply_unet(g, p, x, t, q)
  assert out.shape == (3, 125, 2)
  assert unet1d.count_params(p) == _params_count_by_hand(TINY)


def test_default_config_param_counts():
  shapes = lambda cfg: jax.eval_shape(lambda: unet1d.init_unet(cfg, jax.random.key(0))[1])
  default = UNetConfig(num_tokens=256)
  assert unet1d.count_params(shapes(default)) == _params_count_by_hand(default) == 27_399_298
  reference = UNetConfig(num_tokens=256, attention_levels=())
  n_ref = unet1d.count_params(shapes(reference))
  assert n_ref == _params_count_by_hand(reference)
  assert abs(n_ref - 22.5e6) < 0.1e6  # the official code's 22.5 M (attention only in the middle)


def test_zero_initialised_output_and_token_paths():
  g, p = unet1d.init_unet(TINY, jax.random.key(1))
  x, t, q = _inputs()
  np.testing.assert_array_equal(unet1d.apply_unet(g, p, x, t, q), 0.0)  # zero-init head
  p = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.key(2), a.shape), p)
  cond = unet1d.apply_unet(g, p, x, t, q)
  null = unet1d.apply_unet(g, p, x, t, jnp.full_like(q, TINY.null_token))
  assert np.all(np.isfinite(null)) and not np.allclose(cond, null)
  # each output row depends only on its own row (no batch mixing)
  solo = unet1d.apply_unet(g, p, x[:1], t[:1], q[:1])
  np.testing.assert_allclose(solo, cond[:1], atol=1e-5)


def test_dropout_only_with_key():
  g, p = unet1d.init_unet(TINY, jax.random.key(3))
  p = jax.tree.map(lambda a: a + 0.05, p)
  x, t, q = _inputs()
  a = unet1d.apply_unet(g, p, x, t, q)
  b = unet1d.apply_unet(g, p, x, t, q)
  c = unet1d.apply_unet(g, p, x, t, q, jax.random.key(0))
  np.testing.assert_array_equal(a, b)
  assert not np.allclose(a, c)


def test_no_retracing_across_calls():
  g, p = unet1d.init_unet(TINY, jax.random.key(4))
  traces = []

  @jax.jit
  def f(params, x, t, q):
    traces.append(1)
    return unet1d.apply_unet(g, params, x, t, q)

  for seed in range(3):
    x, t, q = _inputs()
    f(p, x + seed, t, q).block_until_ready()
  assert len(traces) == 1


def test_bad_padding_rejected():
  with pytest.raises(ValueError, match="padded_length"):
    UNetConfig(padded_length=126)


def test_downsampling_is_centred_on_even_inputs():
  """Official convention (stride 2, padding 1): output i sees inputs 2i-1, 2i, 2i+1."""
  down = layers.Downsample(1, rngs=nnx.Rngs(0))
  x = jnp.arange(1.0, 9.0)[None, :, None]  # 1..8 at positions 0..7
  for tap, want in ((0, [0, 2, 4, 6]), (1, [1, 3, 5, 7]), (2, [2, 4, 6, 8])):
    down.conv.kernel[...] = jnp.zeros((3, 1, 1)).at[tap].set(1.0)
    down.conv.bias[...] = jnp.zeros(1)
    np.testing.assert_array_equal(down(x)[0, :, 0], want)


def test_group_norm_epsilon_is_the_official_1e5():
  norm = layers.group_norm(4, 2)
  x = jnp.array([[[0.0, 0.0, 0.0, 0.0], [2e-3, 2e-3, 2e-3, 2e-3]]])  # (1, 2, 4): var 1e-6
  want = np.array([-1e-3, 1e-3]) / np.sqrt(1e-6 + 1e-5)  # per group, (x - mean) / sqrt(var + eps)
  np.testing.assert_allclose(norm(x)[0, :, 0], want, rtol=1e-4)


EGO = tiny_nets.unet_config(5, cond_dim=13)


def test_conditioning_vector_shapes_params_and_null_branch():
  g, p = unet1d.init_unet(EGO, jax.random.key(5))
  e = EGO.emb_mult * EGO.base_channels
  # the token-only count plus the two-layer MLP of the conditioning vector
  assert unet1d.count_params(p) == _params_count_by_hand(EGO) + 13 * e + e + e * e + e
  p = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.key(6), a.shape), p)
  x, t, q = _inputs()
  c1 = jax.random.normal(jax.random.key(7), (3, 13))
  c2 = c1.at[:, 1].add(1.0)
  out = unet1d.apply_unet(g, p, x, t, q, cond=c1)
  assert out.shape == (3, 125, 2)
  null = jnp.full_like(q, EGO.null_token)
  # the unconditional (null-token) branch still depends on the conditioning vector
  assert not np.allclose(
      unet1d.apply_unet(g, p, x, t, null, cond=c1), unet1d.apply_unet(g, p, x, t, null, cond=c2)
  )
  assert not np.allclose(out, unet1d.apply_unet(g, p, x, t, q, cond=c2))
  np.testing.assert_array_equal(out, unet1d.apply_unet(g, p, x, t, q, cond=c1))
  solo = unet1d.apply_unet(g, p, x[1:2], t[1:2], q[1:2], cond=c1[1:2])
  np.testing.assert_allclose(solo, out[1:2], atol=1e-5)


def test_conditioning_mlp_hidden_widths():
  """cond_hidden = (h1, h2): cond_dim -> h1 -> h2 -> embedding, SiLU between; () is one
  hidden layer of the embedding width (as before the field)."""
  e = EGO.emb_mult * EGO.base_channels
  wide = dataclasses.replace(EGO, cond_hidden=(48, 24))
  g, p = unet1d.init_unet(wide, jax.random.key(5))
  assert p["cond_mlp1"]["kernel"].shape == (13, 48)
  assert p["cond_mlp_hidden"][0]["kernel"].shape == (48, 24)
  assert p["cond_mlp2"]["kernel"].shape == (24, e)
  assert unet1d.count_params(p) == (
      _params_count_by_hand(EGO) + 13 * 48 + 48 + 48 * 24 + 24 + 24 * e + e
  )
  same = unet1d.init_unet(dataclasses.replace(EGO, cond_hidden=(e,)), jax.random.key(5))[1]
  default = unet1d.init_unet(EGO, jax.random.key(5))[1]
  assert jax.tree.all(jax.tree.map(np.array_equal, same, default))
  with pytest.raises(ValueError, match="cond_hidden"):
    dataclasses.replace(EGO, cond_hidden=(0,))
  # the forward pass is the MLP written out by hand
  x, t, q = _inputs()
  c = jax.random.normal(jax.random.key(7), (3, 13))
  layer = lambda h, name: h @ name["kernel"] + name["bias"]
  h = jax.nn.silu(layer(jax.nn.silu(layer(c, p["cond_mlp1"])), p["cond_mlp_hidden"][0]))
  time_emb = jax.nn.silu(layer(unet1d.timestep_embedding(t, EGO.base_channels), p["time_mlp1"]))
  want = (
      layer(time_emb, p["time_mlp2"]) + p["token_embed"]["embedding"][q] + layer(h, p["cond_mlp2"])
  )
  model = nnx.merge(g, p)
  np.testing.assert_allclose(model.embedding(t, q, c), want, rtol=1e-5, atol=1e-5)


def test_conditioning_vector_required_iff_configured():
  g, p = unet1d.init_unet(EGO, jax.random.key(8))
  x, t, q = _inputs()
  with pytest.raises(ValueError, match="cond_dim=13"):
    unet1d.apply_unet(g, p, x, t, q)
  g0, p0 = unet1d.init_unet(TINY, jax.random.key(8))
  with pytest.raises(ValueError, match="cond_dim=0"):
    unet1d.apply_unet(g0, p0, x, t, q, cond=jnp.zeros((3, 13)))


def test_abstract_build_matches_init_and_runs_once_per_config():
  """`abstract_params` has init's shapes and dtypes, a fresh dict each call; the graphdef
  merges with init's parameters to the same forward pass; one build per config."""
  cfg = dataclasses.replace(TINY, base_channels=24)  # a config no other test builds
  graphdef, params = unet1d.init_unet(cfg, jax.random.key(1))
  before = unet1d.functional._abstract.cache_info()
  abstract = unet1d.abstract_params(cfg)
  assert jax.tree.map(lambda a: (a.shape, a.dtype), abstract) == jax.tree.map(
      lambda p: (p.shape, p.dtype), params
  )
  abstract.clear()  # the caller's dict: the next call is not affected
  assert unet1d.abstract_params(cfg).keys() == params.keys()
  x, t, q = _inputs()
  np.testing.assert_array_equal(
      unet1d.apply_unet(unet1d.make_graphdef(cfg), params, x, t, q),
      unet1d.apply_unet(graphdef, params, x, t, q),
  )
  after = unet1d.functional._abstract.cache_info()
  assert (after.misses - before.misses, after.hits - before.hits) == (1, 2)
