"""The mixture density network and its loss: shapes and the std floor, the mixture
log-likelihood against scipy.stats, padding rows, where the warm-up's gradient goes, and
the seed fixing the parameters."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special, stats

from cvmdx_jax import constants
from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.config.mdn import MixtureDensityConfig
from cvmdx_jax.models import mdn
from cvmdx_jax.models import multiple_choice as mc
from cvmdx_jax.train import mdn as mdn_train
from tests.models import tiny_nets

CFG = MixtureDensityConfig(
    num_tokens=5, num_hypotheses=3, token_dim=4, hidden=(8,), std_floor_m=0.05
)


def _mixture(b=2, k=3, t=4, seed=0):
  rng = np.random.default_rng(seed)
  return (
      rng.normal(size=(b, k, t, 2)).astype(np.float32),
      rng.uniform(0.2, 2.0, (b, k, t, 2)).astype(np.float32),
      rng.normal(size=(b, k)).astype(np.float32),
      rng.normal(size=(b, t, 2)).astype(np.float32),
  )


def test_shapes_floor_and_the_means_are_the_multiple_choice_rollout():
  graphdef, params = mdn.init(CFG, jax.random.key(0))
  x = tiny_nets.mlp_inputs()
  means, stds, logits = jax.jit(lambda p: mdn.mixture(graphdef, p, CFG, **x))(params)
  assert means.shape == stds.shape == (4, 3, constants.T_PRED, 2) and logits.shape == (4, 3)
  assert np.all(np.asarray(stds) > CFG.std_floor_m) and np.all(np.isfinite(means))
  # the trunk and mean heads are the multiple-choice MLP's: same parameters, same means
  mlp_params = {k: v for k, v in params.items() if k != "log_std"}
  mlp_graphdef = mc.make_graphdef(
      mc.MultipleChoiceConfig(
          **{f.name: getattr(CFG, f.name) for f in dataclasses.fields(mc.MultipleChoiceConfig)}
      )
  )
  traj, probs = mc.hypotheses(mlp_graphdef, mlp_params, CFG, **x)
  np.testing.assert_allclose(means, traj, rtol=1e-6, atol=1e-5)
  np.testing.assert_allclose(jax.nn.softmax(logits), probs, rtol=1e-6)
  # a very negative log-std output leaves exactly the floor
  params["log_std"]["bias"] = jnp.full_like(params["log_std"]["bias"], -200.0)
  params["log_std"]["kernel"] = jnp.zeros_like(params["log_std"]["kernel"])
  _, floored, _ = mdn.mixture(graphdef, params, CFG, **x)
  np.testing.assert_array_equal(floored, np.float32(CFG.std_floor_m))


def test_log_likelihood_equals_scipy():
  means, stds, logits, future = _mixture()
  got = mdn.log_likelihood(means, stds, logits, future)
  weights = special.softmax(logits.astype(np.float64), axis=-1)
  for i in range(len(future)):
    per_mode = [
        stats.multivariate_normal(means[i, k].ravel(), np.diag(stds[i, k].ravel() ** 2)).logpdf(
            future[i].ravel()
        )
        for k in range(means.shape[1])
    ]
    expected = special.logsumexp(per_mode, b=weights[i])
    np.testing.assert_allclose(got[i], expected, rtol=1e-5)
    np.testing.assert_allclose(mdn.mode_log_densities(means, stds, future)[i], per_mode, rtol=1e-5)


def test_one_mode_one_step_by_hand():
  """K = 1, T = 1: log N(y; mu, s^2) per coordinate, summed: y = (1, 0), mu = 0, s = 1
  gives -(1/2) - log(2 pi)."""
  got = mdn.log_likelihood(
      jnp.zeros((1, 1, 1, 2)), jnp.ones((1, 1, 1, 2)), jnp.zeros((1, 1)), jnp.array([[[1.0, 0.0]]])
  )
  np.testing.assert_allclose(got, [-0.5 - np.log(2 * np.pi)], rtol=1e-6)


def test_padding_rows_change_neither_loss_nor_gradient():
  means, stds, logits, future = _mixture(b=3)
  weight = jnp.array([1.0, 1.0, 0.0])

  def loss(m, s, lg, fut, w, warm_up):
    return mdn_train.mdn_loss(m, s, lg, fut, w, warm_up=warm_up, cls_weight=1.0)[0]

  for warm_up in (False, True):
    full = loss(means, stds, logits, future, weight, warm_up)
    cut = loss(means[:2], stds[:2], logits[:2], future[:2], weight[:2], warm_up)
    np.testing.assert_allclose(full, cut, rtol=1e-6)
    grads = jax.grad(loss, argnums=(0, 1, 2))(means, stds, logits, future, weight, warm_up)
    for g in grads:
      np.testing.assert_array_equal(g[2], 0.0)
  # the mixture loss is the mean NLL per coordinate of the unpadded rows
  nll = -mdn.log_likelihood(means[:2], stds[:2], logits[:2], future[:2])
  np.testing.assert_allclose(
      loss(means, stds, logits, future, weight, False),
      np.mean(nll) / (future.shape[1] * 2),
      rtol=1e-6,
  )


def test_warm_up_moves_only_the_winner_and_its_std():
  """In the warm-up the mean closest by ADE (mode 1 here) gets the regression gradient,
  the stds only the winner's Gaussian NLL; without it every mode gets a gradient."""
  means, stds, logits, _ = _mixture(b=1, t=4)
  future = means[:, 1] + 0.1

  def grads(warm_up):
    return jax.grad(
        lambda m, s: mdn_train.mdn_loss(
            m, s, logits, future, jnp.ones(1), warm_up=warm_up, cls_weight=1.0
        )[0],
        argnums=(0, 1),
    )(means, stds)

  g_means, g_stds = grads(True)
  for g in (g_means, g_stds):
    assert np.all(np.asarray(g[0, [0, 2]]) == 0) and np.any(np.asarray(g[0, 1]) != 0)
  g_means, g_stds = grads(False)
  assert all(np.any(np.asarray(g[0, k]) != 0) for g in (g_means, g_stds) for k in range(3))


def test_the_seed_fixes_the_parameters():
  same = jax.tree.map(
      np.array_equal, mdn.init(CFG, jax.random.key(3))[1], mdn.init(CFG, jax.random.key(3))[1]
  )
  assert all(jax.tree.leaves(same))
  differ = jax.tree_util.tree_leaves_with_path(
      jax.tree.map(
          lambda a, b: bool(np.any(a != b)),
          mdn.init(CFG, jax.random.key(3))[1],
          mdn.init(CFG, jax.random.key(4))[1],
      )
  )
  random = [
      d for path, d in differ if jax.tree_util.keystr(path).endswith(("kernel']", "embedding']"))
  ]
  assert len(random) == 5 and all(random)  # embedding, hidden, controls, logits, log_std


def test_a_bad_floor_is_refused_naming_the_field():
  with pytest.raises(ConfigFieldError, match="std_floor_m"):
    MixtureDensityConfig(std_floor_m=0.0)
