"""fit_hypotheses: output contract, sklearn agreement, mode recovery."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from cvmdx_jax.config.sampling import HypothesisConfig
from cvmdx_jax.multimodal import hypotheses, synthetic
from tests.multimodal import oracle

fit_hypotheses = jax.jit(hypotheses.fit_hypotheses, static_argnames=("c_max", "config"))


@pytest.fixture(scope="module")
def sets():
  """(trajectories (B, 9, 125, 2), true num_modes, true mode ids) for 300 sets."""
  return synthetic.mode_sets(seed=0, num_sets=300)


@pytest.fixture(scope="module")
def hyps(sets):
  return fit_hypotheses(sets[0])


def test_output_contract(sets, hyps):
  trajectories = sets[0]
  b, n, t, _ = trajectories.shape
  assert hyps.num_modes.shape == (b,) and hyps.labels.shape == (b, n)
  assert hyps.means.shape == (b, 3, t, 2)
  assert hyps.probs.shape == (b, 3) and hyps.bic.shape == (b, 3)
  num_modes, labels = np.asarray(hyps.num_modes), np.asarray(hyps.labels)
  probs, means = np.asarray(hyps.probs), np.asarray(hyps.means)
  assert np.all((num_modes >= 1) & (num_modes <= 3))
  assert np.all((labels >= 0) & (labels < num_modes[:, None]))
  np.testing.assert_allclose(probs.sum(axis=1), 1.0, rtol=1e-6)
  assert np.all(np.diff(probs, axis=1) <= 0)  # slot 0 is the most likely
  for i in range(b):
    k = num_modes[i]
    assert np.all(probs[i, :k] > 0) and np.all(probs[i, k:] == 0)
    assert np.all(means[i, k:] == 0)
    for slot in range(k):
      assigned = labels[i] == slot
      np.testing.assert_allclose(probs[i, slot], assigned.mean(), rtol=1e-6)
      np.testing.assert_allclose(
          means[i, slot], trajectories[i][assigned].mean(axis=0), rtol=1e-5, atol=1e-3
      )


def test_recovers_true_modes_and_partition(sets, hyps):
  _, num_modes, mode_ids = sets
  found = np.asarray(hyps.num_components)
  assert np.mean(found == num_modes) >= 0.95
  # Where C is right, the partition is the true one up to relabelling and the
  # probabilities are the true shares, sorted.
  labels, probs = np.asarray(hyps.labels), np.asarray(hyps.probs)
  right = np.flatnonzero(found == num_modes)
  same_partition = [
      all(len(set(labels[i][mode_ids[i] == m])) == 1 for m in range(num_modes[i])) for i in right
  ]
  assert np.mean(same_partition) >= 0.99
  for i in right[same_partition]:
    shares = np.sort(np.bincount(mode_ids[i], minlength=3) / 9.0)[::-1]
    np.testing.assert_allclose(probs[i], shares, rtol=1e-6)


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.ConvergenceWarning")
def test_selected_c_agrees_with_sklearn(sets, hyps):
  want = oracle.fit_batch(sets[0], HypothesisConfig()).argmin(axis=1) + 1
  assert np.mean(np.asarray(hyps.num_components) == want) >= 0.98


def test_single_component_bic_is_closed_form_on_sklearn_pca_points(sets, hyps):
  config = HypothesisConfig()
  for i in range(10):
    points = oracle.embed(sets[0][i], config)
    cov = np.cov(points.T, bias=True) + config.reg_covar * np.eye(2)
    log_like = stats.multivariate_normal(points.mean(axis=0), cov).logpdf(points).sum()
    want = -2 * log_like + 5 * np.log(9)
    np.testing.assert_allclose(float(hyps.bic[i, 0]), want, rtol=1e-4, atol=1e-3)


def test_minmax_with_small_floor_over_selects():
  trajectories, num_modes, _ = synthetic.mode_sets(seed=1, num_sets=200)
  physical = np.asarray(fit_hypotheses(trajectories).num_components)
  minmax = np.asarray(
      fit_hypotheses(
          trajectories, config=HypothesisConfig(scaling="minmax", reg_covar=9e-5)
      ).num_components
  )
  assert np.mean(minmax == num_modes) < 0.8 < np.mean(physical == num_modes)
  assert np.mean(minmax > num_modes) > 2 * np.mean(minmax < num_modes)


def test_no_retrace_for_new_values_of_same_shape(sets):
  first = jnp.asarray(sets[0][:8])
  fit_hypotheses(first)
  before = fit_hypotheses._cache_size()
  out = fit_hypotheses(first + 5.0)
  fit_hypotheses(jnp.asarray(sets[0][8:16]))
  assert fit_hypotheses._cache_size() == before
  # Translating every sample shifts the means by the same amount.
  np.testing.assert_allclose(
      np.asarray(out.means[:, 0]), np.asarray(fit_hypotheses(first).means[:, 0]) + 5.0, atol=1e-3
  )


def test_degenerate_identical_samples():
  trajectories = np.broadcast_to(np.linspace([0.0, 0.0], [150.0, 1.0], 125), (2, 9, 125, 2)).astype(
      np.float32
  )
  for scaling in ("physical", "minmax"):
    out = fit_hypotheses(trajectories, config=HypothesisConfig(scaling=scaling))
    np.testing.assert_array_equal(np.asarray(out.num_modes), [1, 1])
    np.testing.assert_allclose(np.asarray(out.means[:, 0]), trajectories[:, 0], atol=1e-4)
    assert np.all(np.isfinite(np.asarray(out.bic)))


def test_c_max_and_bad_input():
  trajectories = synthetic.mode_sets(seed=2, num_sets=4)[0]
  out = fit_hypotheses(trajectories, c_max=2)
  assert out.probs.shape == (4, 2) and out.bic.shape == (4, 2)
  with pytest.raises(ValueError, match="contradicts"):
    fit_hypotheses(trajectories, c_max=2, config=HypothesisConfig(c_max=3))
  with pytest.raises(ValueError, match=r"\(B, N, T, 2\)"):
    fit_hypotheses(trajectories[0])
  with pytest.raises(ValueError, match="exceeds N"):
    fit_hypotheses(trajectories[:, :2], c_max=3)
  with pytest.raises(ValueError, match="HypothesisConfig.scaling"):
    HypothesisConfig(scaling="zscore")
  with pytest.raises(ValueError, match="reg_covar"):
    HypothesisConfig(reg_covar=0.0)


def test_temper_is_the_renormalised_power_and_keeps_empty_slots_and_order():
  shares = jnp.asarray([[0.5, 0.3, 0.2], [0.75, 0.25, 0.0]])
  out = np.asarray(hypotheses.temper(shares, 0.5))
  root = np.sqrt([0.5, 0.3, 0.2])
  np.testing.assert_allclose(out[0], root / root.sum(), rtol=1e-6)
  np.testing.assert_allclose(out[1], [np.sqrt(3) / (np.sqrt(3) + 1), 1 / (np.sqrt(3) + 1), 0.0])
  assert out[1, 2] == 0.0 and np.all(np.diff(out, axis=1) <= 0)
  assert hypotheses.temper(shares, 1.0) is shares  # the paper's share, untouched
  sharp = np.asarray(hypotheses.temper(shares, 3.0))[0]
  np.testing.assert_allclose(sharp, np.array([0.125, 0.027, 0.008]) / 0.16, rtol=1e-6)


@pytest.mark.parametrize("method", ["bic", "kmeans"])
def test_prob_temperature_moves_only_the_probabilities(sets, method):
  trajectories = sets[0][:40]
  plain = fit_hypotheses(trajectories, config=HypothesisConfig(method=method))
  tempered = fit_hypotheses(
      trajectories, config=HypothesisConfig(method=method, prob_temperature=0.6)
  )
  for field in ("num_modes", "num_components", "labels", "means"):
    np.testing.assert_array_equal(getattr(tempered, field), getattr(plain, field))
  np.testing.assert_allclose(tempered.probs, hypotheses.temper(plain.probs, 0.6), rtol=1e-6)
  # flatter than the shares, still a distribution in descending order
  assert np.all(np.asarray(tempered.probs)[:, 0] <= np.asarray(plain.probs)[:, 0] + 1e-7)
  np.testing.assert_allclose(np.asarray(tempered.probs).sum(axis=1), 1.0, rtol=1e-6)


@pytest.mark.parametrize("bad", [0.0, -0.5])
def test_prob_temperature_must_be_positive(bad):
  with pytest.raises(ValueError, match="prob_temperature"):
    HypothesisConfig(prob_temperature=bad)
