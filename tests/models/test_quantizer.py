"""VQ / CVQ quantiser: nearest entry, losses, straight-through, usage, dead-entry revival."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats
from flax import nnx

from cvmdx_jax.config.models import EncoderConfig, QuantizerConfig, TokenizerConfig
from cvmdx_jax.models import quantizer as qz
from cvmdx_jax.models import tokenizer as tok


def test_quantize_matches_numpy_nearest_and_losses():
  rng = np.random.default_rng(0)
  codebook = rng.normal(size=(7, 3)).astype(np.float32)
  z = rng.normal(size=(11, 3)).astype(np.float32)
  out = jax.jit(qz.quantize)(codebook, z)
  expected = np.argmin(((z[:, None] - codebook[None]) ** 2).sum(-1), axis=1)
  np.testing.assert_array_equal(out.indices, expected)
  np.testing.assert_allclose(out.z_q, codebook[expected], atol=1e-6)
  sq = ((z - codebook[expected]) ** 2).mean(-1)
  np.testing.assert_allclose(out.codebook_loss, sq, rtol=1e-5)
  np.testing.assert_allclose(out.commitment_loss, sq, rtol=1e-5)


def test_straight_through_gradient_is_identity_and_losses_split():
  codebook = jnp.array([[0.0, 0.0], [1.0, 1.0]])
  z = jnp.array([[0.2, -0.1], [0.9, 1.3]])
  w = jnp.array([[1.0, 2.0], [3.0, 4.0]])
  g = jax.grad(lambda z: jnp.sum(qz.quantize(codebook, z).z_q * w))(z)
  np.testing.assert_allclose(g, w)
  # codebook loss trains only the codebook, commitment only the encoder side.
  g_cb = jax.grad(lambda c, z: qz.quantize(c, z).codebook_loss.sum(), argnums=(0, 1))
  gc, gz = g_cb(codebook, z)
  assert np.all(np.asarray(gz) == 0) and np.any(np.asarray(gc) != 0)
  g_cm = jax.grad(lambda c, z: qz.quantize(c, z).commitment_loss.sum(), argnums=(0, 1))
  gc, gz = g_cm(codebook, z)
  assert np.all(np.asarray(gc) == 0)
  np.testing.assert_allclose(gz, (z - codebook[jnp.array([0, 1])]), rtol=1e-6)


def test_straight_through_reaches_encoder(scenarios_factory):
  cfg = TokenizerConfig(
      EncoderConfig(latent_dim=4, channels=(8, 8), kernel_size=3),
      QuantizerConfig(codebook_size=5, latent_dim=4),
  )
  model = tok.Tokenizer(cfg, rngs=nnx.Rngs(0))
  graphdef, params = nnx.split(model, nnx.Param)
  s = scenarios_factory(6)

  def recon_only(params):  # no commitment term: the encoder is reached only through z_q
    out = nnx.merge(graphdef, params)(jnp.asarray(s.xi), jnp.asarray(s.mask))
    return jnp.mean(out.reconstruction**2) + jnp.mean(out.logits**2)

  grads = jax.jit(jax.grad(recon_only))(params)
  enc = jax.tree.leaves(grads["encoder"])
  assert all(np.all(np.isfinite(g)) for g in enc)
  assert all(float(jnp.abs(g).max()) > 0 for g in enc)


def test_batch_share_ignores_padding_and_perplexity_matches_scipy():
  idx = jnp.array([0, 0, 1, 2, 2, 2, 3])
  weight = jnp.array([1, 1, 1, 1, 1, 1, 0.0])
  np.testing.assert_allclose(qz.batch_share(idx, weight, 5), [2 / 6, 1 / 6, 3 / 6, 0, 0], rtol=1e-6)
  in_use, ppl = qz.codebook_stats(idx, 5, weight)
  assert int(in_use) == 3
  np.testing.assert_allclose(ppl, np.exp(scipy.stats.entropy([2, 1, 3])), rtol=1e-5)


def test_cvq_anchors_come_only_from_weighted_rows():
  cfg = QuantizerConfig(kind="cvq", codebook_size=16, latent_dim=2)
  z = jnp.concatenate([jnp.zeros((4, 2)), jnp.full((4, 2), 1e6)])
  weight = jnp.array([1.0] * 4 + [0.0] * 4)
  codebook, usage = qz.update_codebook(
      jnp.ones((16, 2)),
      qz.init_usage(cfg),
      z,
      jnp.zeros(8, jnp.int32),
      weight,
      jax.random.key(0),
      cfg,
  )
  # entry 0 (used) stays, the unused ones move toward the zero rows, none toward 1e6.
  np.testing.assert_allclose(codebook[0], [1.0, 1.0])
  assert float(jnp.abs(codebook[1:]).max()) < 0.01
  np.testing.assert_allclose(usage[0], 0.01, rtol=1e-5)  # (1 - gamma) * share 1


def test_vq_update_leaves_codebook_alone():
  cfg = QuantizerConfig(kind="vq", codebook_size=4, latent_dim=2)
  cb = jnp.arange(8.0).reshape(4, 2)
  new, _ = qz.update_codebook(
      cb,
      qz.init_usage(cfg),
      jnp.zeros((3, 2)),
      jnp.zeros(3, jnp.int32),
      jnp.ones(3),
      jax.random.key(0),
      cfg,
  )
  np.testing.assert_array_equal(new, cb)


@functools.partial(jax.jit, static_argnums=(0,))
def _train_codebook(cfg, codebook, data):
  """SGD on the codebook loss (frozen identity encoder) + the quantiser's update."""

  def step(carry, i):
    codebook, usage = carry
    key = jax.random.fold_in(jax.random.key(1), i)
    z = data[jax.random.choice(jax.random.fold_in(key, 1), data.shape[0], (64,))]
    grad = jax.grad(lambda c: qz.quantize(c, z).codebook_loss.mean())(codebook)
    codebook = codebook - 0.5 * grad
    idx = qz.nearest(codebook, z)
    return qz.update_codebook(codebook, usage, z, idx, jnp.ones(64), key, cfg), None

  (codebook, _), _ = jax.lax.scan(step, (codebook, qz.init_usage(cfg)), jnp.arange(600))
  return qz.codebook_stats(qz.nearest(codebook, data), cfg.codebook_size)


def test_cvq_revives_entries_that_vq_leaves_dead():
  rng = np.random.default_rng(0)
  centres = 5.0 * np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], 1)
  data = jnp.asarray(
      (centres[rng.integers(0, 8, 2000)] + rng.normal(0, 0.1, (2000, 2))).astype(np.float32)
  )
  # Entries on a line outside the ring: at first one entry is nearest to every cluster,
  # and VQ's losers (no members, no codebook gradient) never move.
  codebook = jnp.asarray(
      np.stack([np.linspace(7, 9, 8), rng.normal(0, 0.1, 8)], 1).astype(np.float32)
  )
  assert int(qz.codebook_stats(qz.nearest(codebook, data), 8)[0]) == 1
  vq_use, vq_ppl = _train_codebook(QuantizerConfig("vq", 8, 2), codebook, data)
  cvq_use, cvq_ppl = _train_codebook(QuantizerConfig("cvq", 8, 2), codebook, data)
  assert int(vq_use) <= 4
  assert int(cvq_use) == 8
  assert float(cvq_ppl) > 6.0 > float(vq_ppl)
