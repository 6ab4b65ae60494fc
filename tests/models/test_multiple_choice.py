"""The multiple-choice MLP and its winner-takes-all loss: shapes, the residual base against
closed-form kinematics, the winner on hand-made hypotheses, and where the gradient goes."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cvmdx_jax import constants, ego_motion
from cvmdx_jax.config.models import MultipleChoiceConfig
from cvmdx_jax.models import multiple_choice as mc
from cvmdx_jax.train import baseline
from tests.models import tiny_nets

T = np.arange(1, constants.T_PRED + 1) * constants.DT  # s after t0
CFG = MultipleChoiceConfig(num_tokens=5, num_hypotheses=3, token_dim=4, hidden=(8,))


def _line(dx, dy):
  return np.linspace(0, 1, constants.T_PRED)[:, None] * np.array([dx, dy], np.float32)


def test_shapes_and_probabilities():
  graphdef, params = mc.init(CFG, jax.random.key(0))
  x = tiny_nets.mlp_inputs()
  controls, logits = jax.jit(lambda p: mc.apply(graphdef, p, x["q"], x["delta"], x["ego"]))(params)
  assert controls.shape == (4, 3, constants.T_PRED, 2) and logits.shape == (4, 3)
  traj, probs = mc.hypotheses(graphdef, params, CFG, **x)
  assert traj.shape == (4, 3, constants.T_PRED, 2)
  np.testing.assert_allclose(np.sum(probs, -1), 1.0, rtol=1e-6)
  assert np.all(np.isfinite(traj))
  # the heads start apart (WTA needs distinct heads) but near the residual base
  assert np.min(np.ptp(np.asarray(traj[:, :, -1, 1]), axis=1)) > 0


def test_zero_output_is_the_decayed_constant_acceleration_closed_form():
  """A head that outputs 0 drives the residual base: with tau_a = 1e12 s (a finite
  stand-in for no decay: exp(-5 / 1e12) is 1 in float32) a constant a_x,
  x = v0 t + a t^2 / 2 (the VMM integrates exactly for constant a and no yaw rate)."""
  cfg = dataclasses.replace(CFG, residual_decay_s=(1e12, 0.1))
  ego = np.zeros((2, ego_motion.NUM_FEATURES), np.float32)
  ego[1, 1] = 0.5  # feature 1 = a_x / (1 m/s^2)
  v0 = np.array([25.0, 20.0], np.float32)
  traj = mc.rollout(cfg, jnp.zeros((2, 3, constants.T_PRED, 2)), jnp.asarray(ego), v0, jnp.zeros(2))
  for i, a in enumerate((0.0, 0.5)):
    for k in range(3):
      np.testing.assert_allclose(traj[i, k, :, 0], v0[i] * T + a * T**2 / 2, rtol=1e-5)
      np.testing.assert_allclose(traj[i, k, :, 1], 0.0, atol=1e-5)


def test_wta_picks_the_closest_head_and_matches_hand_computed_loss():
  gt = np.stack([_line(100, 0), _line(100, 3.5)])
  heads = np.stack(
      [
          np.stack([_line(100, 3.5), _line(102, 0), _line(100, -3.5)]),
          np.stack([_line(100, 3.0), _line(100, 0), _line(90, 3.5)]),
      ]
  )
  logits = np.array([[0.0, 1.0, -1.0], [2.0, 0.0, 0.0]], np.float32)
  loss, parts = baseline.wta_loss(
      jnp.asarray(heads), jnp.asarray(logits), jnp.asarray(gt), jnp.ones(2), cls_weight=0.5
  )
  assert parts["winner"].tolist() == [1, 0]
  # ADE of a line whose end is off by (dx, dy): mean of |(dx, dy)| s over s in [0, 1]
  ade = [np.hypot(2, 0) / 2, np.hypot(0, 0.5) / 2]
  ce = [
      np.log(np.exp(logits[0]).sum()) - logits[0, 1],
      np.log(np.exp(logits[1]).sum()) - logits[1, 0],
  ]
  np.testing.assert_allclose(parts["wta_ade"], np.mean(ade), rtol=1e-4)
  np.testing.assert_allclose(parts["cross_entropy"], np.mean(ce), rtol=1e-5)
  np.testing.assert_allclose(loss, np.mean(ade) + 0.5 * np.mean(ce), rtol=1e-4)


def test_padding_rows_do_not_count():
  rng = np.random.default_rng(1)
  heads = jnp.asarray(rng.normal(size=(5, 3, constants.T_PRED, 2)), jnp.float32)
  logits = jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)
  gt = jnp.asarray(rng.normal(size=(5, constants.T_PRED, 2)), jnp.float32)
  padded, _ = baseline.wta_loss(heads, logits, gt, jnp.asarray([1, 1, 1, 0, 0.0]), 1.0)
  sliced, _ = baseline.wta_loss(heads[:3], logits[:3], gt[:3], jnp.ones(3), 1.0)
  np.testing.assert_allclose(padded, sliced, rtol=1e-6)


def test_gradient_reaches_only_the_winners_regression_head():
  graphdef, params = mc.init(CFG, jax.random.key(3))
  x = tiny_nets.mlp_inputs(b=1, seed=2)
  traj, _ = baseline.forward(graphdef, params, CFG, x)
  winner = 2
  # a truth right beside head 2's trajectory, far from the others
  gt = traj[:, winner] + jnp.asarray([0.1, -0.05])

  def loss(p):
    t, logits = baseline.forward(graphdef, p, CFG, x)
    return baseline.wta_loss(t, logits, gt, jnp.ones(1), 1.0)

  (_, parts), grads = jax.value_and_grad(loss, has_aux=True)(params)
  assert int(parts["winner"][0]) == winner
  kernel = np.asarray(grads["controls"]["kernel"]).reshape(-1, 3, constants.T_PRED, 2)
  bias = np.asarray(grads["controls"]["bias"]).reshape(3, constants.T_PRED, 2)
  for k in range(3):
    if k == winner:
      assert np.abs(kernel[:, k]).max() > 0 and np.abs(bias[k]).max() > 0
    else:
      assert not kernel[:, k].any() and not bias[k].any()
  assert np.all(np.abs(np.asarray(grads["logits"]["bias"])) > 0)  # the classifier: every head


def test_config_refuses_bad_sizes():
  with pytest.raises(ValueError, match=r"hidden=\(8, 0\): must be > 0"):
    MultipleChoiceConfig(hidden=(8, 0))
  with pytest.raises(ValueError, match="two"):
    MultipleChoiceConfig(control_scale=(4.0,))
