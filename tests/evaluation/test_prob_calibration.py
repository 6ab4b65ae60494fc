"""The p(c) temperature chosen on val: hand-worked log losses, recovery of a known
temperature, the tie rule, the closest hypothesis among the non-empty ones, and the
predictor it gives."""

import dataclasses

import numpy as np
import pytest

from cvmdx_jax.config.sampling import HypothesisConfig, SamplingConfig
from cvmdx_jax.evaluation import prob_calibration
from cvmdx_jax.multimodal import hypotheses


def test_log_losses_by_hand():
  shares = np.array([[0.75, 0.25, 0.0], [0.5, 0.5, 0.0]])
  closest = np.array([1, 0])
  losses = prob_calibration.log_losses(shares, closest, (1.0, 0.5))
  p_half = 0.5 / (np.sqrt(0.75) + 0.5)  # sqrt(0.25) / (sqrt(0.75) + sqrt(0.25))
  np.testing.assert_allclose(
      losses, [-(np.log(0.25) + np.log(0.5)) / 2, -(np.log(p_half) + np.log(0.5)) / 2], rtol=1e-6
  )


def test_a_closest_hypothesis_given_no_probability_costs_the_floor():
  losses = prob_calibration.log_losses(np.array([[1.0, 0.0, 0.0]]), np.array([2]), (0.5,))
  np.testing.assert_allclose(losses, [-np.log(1e-6)])


@pytest.mark.parametrize("true_t", [0.5, 0.8])
def test_recovers_the_temperature_that_generated_the_closest_hypotheses(true_t):
  rng = np.random.default_rng(0)
  shares = np.sort(rng.dirichlet([2.0, 1.0, 0.5], size=20_000), axis=1)[:, ::-1]
  truth = np.asarray(hypotheses.temper(shares, true_t), np.float64)
  u = rng.random(len(shares))[:, None]
  closest = np.minimum((u > np.cumsum(truth, axis=1)).sum(axis=1), 2)
  losses = prob_calibration.log_losses(shares, closest)
  assert prob_calibration.choose(losses) == true_t


def test_ties_take_the_temperature_nearest_one():
  grid = (0.3, 0.6, 0.9, 1.0)
  assert prob_calibration.choose([0.5, 0.4, 0.4, 0.7], grid) == 0.9
  assert prob_calibration.choose([0.4, 0.4, 0.4, 0.4], grid) == 1.0


def test_the_closest_hypothesis_is_a_non_empty_one():
  t = np.linspace(0, 1, 5)[:, None] * np.array([1.0, 0.0])
  means = np.stack([t, t + [0.0, 3.0], t + [0.0, 0.1]])[None]  # (1, 3, 5, 2)
  gt = t[None]
  assert prob_calibration.closest_hypothesis(means, np.array([[0.5, 0.5, 0.0]]), gt)[0] == 0
  assert prob_calibration.closest_hypothesis(means, np.array([[0.0, 0.5, 0.5]]), gt)[0] == 2


def test_with_temperature_changes_only_the_hypotheses_temperature():
  @dataclasses.dataclass(frozen=True)
  class Holder:  # stands for a Predictor: a dataclass with `sampling`
    sampling: SamplingConfig
    name: str = "run"

  sampling = SamplingConfig(num_samples=64, hypotheses=HypothesisConfig(method="kmeans"))
  out = prob_calibration.with_temperature(Holder(sampling), 0.6)
  assert out.sampling.hypotheses.prob_temperature == 0.6 and out.name == "run"
  assert out.sampling == dataclasses.replace(
      sampling,
      hypotheses=dataclasses.replace(sampling.hypotheses, prob_temperature=0.6),
  )


def test_closest_log_loss_per_scenario_by_hand():
  probs = np.array([[0.5, 0.3, 0.2], [0.0, 1.0, 0.0]])
  np.testing.assert_allclose(
      prob_calibration.closest_log_loss(probs, np.array([2, 0])), [-np.log(0.2), -np.log(1e-6)]
  )
