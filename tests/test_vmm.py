"""VMM rollout and its inverse against numpy loops, closed forms and the cVMD example files."""

import glob
import math

import jax
import numpy as np
import scipy.io

from cvmdx_jax import vmm
from cvmdx_jax.evaluation import baselines


def numpy_rollout(controls, v0, psi0, dt=0.04):
  """The paper's step; a step that would end below 0 m/s is cut at the stop time v / -a."""
  x = y = 0.0
  v, psi = v0, psi0
  out = []
  for a, w in controls:
    tau = dt if v + a * dt >= 0 else v / -a
    x += v * math.cos(psi) * tau + (a * math.cos(psi) - w * v * math.sin(psi)) * tau**2 / 2
    y += v * math.sin(psi) * tau + (a * math.sin(psi) + w * v * math.cos(psi)) * tau**2 / 2
    v = max(v + a * tau, 0.0)
    psi += w * tau
    out.append((x, y))
  return np.array(out)


def test_matches_numpy_loop_and_vmaps():
  rng = np.random.default_rng(0)
  controls = rng.normal(0, [1.0, 0.05], size=(3, 4, 125, 2)).astype(np.float32)
  v0 = rng.uniform(20, 35, (3, 4)).astype(np.float32)
  psi0 = rng.normal(0, 0.02, (3, 4)).astype(np.float32)
  out = np.asarray(jax.jit(vmm.rollout)(controls, v0, psi0))
  assert out.shape == (3, 4, 125, 2)
  for i in range(3):
    for j in range(4):
      np.testing.assert_allclose(
          out[i, j], numpy_rollout(controls[i, j], v0[i, j], psi0[i, j]), atol=2e-3
      )
  per_sample = jax.vmap(jax.vmap(vmm.rollout))(controls, v0, psi0)
  np.testing.assert_allclose(per_sample, out, atol=1e-5)


def test_constant_acceleration_straight_line():
  a, v0 = 1.5, 20.0
  out = np.asarray(vmm.rollout(np.tile([a, 0.0], (125, 1)), v0, 0.0))
  t = 0.04 * np.arange(1, 126)
  np.testing.assert_allclose(out[:, 0], v0 * t + 0.5 * a * t**2, rtol=1e-5)
  np.testing.assert_allclose(out[:, 1], 0.0, atol=1e-6)


def test_constant_yaw_rate_arc():
  """Constant speed and yaw rate: the exact circle differs from the
  second-order step by O(dt^3) per step; 125 steps stay within 2 cm."""
  w, v0, psi0 = 0.2, 25.0, 0.1
  out = np.asarray(vmm.rollout(np.tile([0.0, w], (125, 1)), v0, psi0), np.float64)
  t = 0.04 * np.arange(1, 126)
  r = v0 / w
  x = r * (np.sin(psi0 + w * t) - np.sin(psi0))
  y = -r * (np.cos(psi0 + w * t) - np.cos(psi0))
  np.testing.assert_allclose(out, np.stack([x, y], -1), atol=0.02)
  np.testing.assert_allclose(
      np.linalg.norm(out - [-r * math.sin(psi0), r * math.cos(psi0)], axis=-1), r, rtol=1e-3
  )


def test_reproduces_cvmd_example_files(shared_dir):
  files = sorted(glob.glob(str(shared_dir / "fixtures/cvmd_mat/*/class*/*.mat")))
  assert len(files) == 6
  for f in files:
    d = scipy.io.loadmat(f)
    controls = np.stack([d["predicted_ax"][0], d["predicted_dpsi"][0]], -1)
    ego_x, ego_y = d["observed_data_x"][0, -1], d["observed_data_y"][0, -1]
    gt = np.stack([d["predicted_x"][0] - ego_x, d["predicted_y"][0] - ego_y], -1)
    out = np.asarray(vmm.rollout(controls, d["v0"][0, 0], d["psi_0"][0, 0]))
    err = np.linalg.norm(out - gt, axis=-1)
    assert err[-1] < 0.3, f  # within 0.3 m at 5 s
    assert err.mean() < 0.2 and err.max() < 0.35, f  # positions are rounded to 1 cm


def test_braking_to_a_stop_equals_closed_form():
  """Constant braking b from v0: s(t) = v0 t - b t^2 / 2 until t_stop = v0 / b (here
  mid-step, 62.5 steps), then s = v0^2 / 2b for good; along the constant heading."""
  b, v0, psi0 = 4.0, 10.0, 0.1
  out = np.asarray(vmm.rollout(np.tile([-b, 0.0], (125, 1)), v0, psi0), np.float64)
  t = 0.04 * np.arange(1, 126)
  s = np.where(t < v0 / b, v0 * t - 0.5 * b * t**2, v0**2 / (2 * b))
  np.testing.assert_allclose(out, s[:, None] * [math.cos(psi0), math.sin(psi0)], atol=1e-4)
  assert np.all(out[63:] == out[62])  # standing still, bit for bit


def test_jam_scenarios_never_move_backwards():
  """v0 near 0 (some exactly 0), mostly strong braking with some throttle and steering."""
  rng = np.random.default_rng(1)
  m = 64
  controls = np.stack([rng.normal(-3.0, 2.5, (m, 125)), rng.normal(0, 0.05, (m, 125))], -1).astype(
      np.float32
  )
  v0 = np.where(np.arange(m) % 4 == 0, 0.0, rng.uniform(0, 0.5, m)).astype(np.float32)
  psi0 = rng.normal(0, 0.02, m).astype(np.float32)
  out = np.asarray(jax.jit(vmm.rollout)(controls, v0, psi0), np.float64)
  for i in range(m):
    ref = numpy_rollout(controls[i].astype(np.float64), float(v0[i]), float(psi0[i]))
    np.testing.assert_allclose(out[i], ref, atol=1e-4)
  # Each step's displacement points along the heading of its start: no reversing.
  heading = psi0[:, None] + np.cumsum(np.r_["-1", np.zeros((m, 1)), controls[:, :-1, 1]], -1) * 0.04
  step = np.diff(np.r_["1", np.zeros((m, 1, 2)), out], axis=1)
  along = step[..., 0] * np.cos(heading) + step[..., 1] * np.sin(heading)
  assert along.min() > -1e-5
  # With a zero yaw rate the path is a ray: x never decreases.
  no_yaw = np.stack([controls[..., 0], np.zeros_like(controls[..., 1])], -1)
  straight = np.asarray(vmm.rollout(no_yaw, v0, 0.0))
  assert np.diff(straight[..., 0], axis=-1).min() >= 0 and np.all(straight[..., 1] == 0)


def test_rollout_gradient_is_finite_through_a_stop():
  grad = jax.grad(lambda c: vmm.rollout(c, 1.0, 0.0)[-1, 0])(np.tile([-4.0, 0.0], (125, 1)))
  assert np.all(np.isfinite(np.asarray(grad)))


def test_constant_acceleration_baseline_brakes_to_a_stop():
  """History braking at 3 m/s^2 down to 2 m/s: stops after 2^2 / 6 m and stays there."""
  t = 0.04 * np.arange(-74, 1)
  xi = np.zeros((1, 9, 75, 4), np.float32)
  xi[0, 0, :, 2] = 2.0 - 3.0 * t
  out = np.asarray(baselines.constant_acceleration_yaw_rate(xi))
  np.testing.assert_allclose(out[0, -1], [4.0 / 6.0, 0.0], atol=1e-3)
  assert np.diff(out[0, :, 0]).min() >= 0


def test_fit_controls_recovers_constant_turn():
  # A closed-form VMM path: constant a and yaw rate -> the fit must return them.
  controls = np.broadcast_to(np.array([0.5, 0.02], np.float32), (3, 125, 2))
  v0, psi0 = np.array([20.0, 30.0, 10.0], np.float32), np.array([0.0, 0.01, -0.02], np.float32)
  future = np.asarray(vmm.rollout(controls, v0, psi0))
  fitted = np.asarray(vmm.fit_controls(future, v0, psi0))
  np.testing.assert_allclose(fitted[:, 2:-2], controls[:, 2:-2], atol=0.02)


def test_fit_controls_of_a_stop_reproduces_it():
  """Closed-form futures braking to a standstill (v0 2-12 m/s, 3-6 m/s^2): the fitted
  controls roll out to them and never reverse (the smoothing penalty rounds off the jerk
  at the stop: 12 cm at most, 5 cm on average)."""
  v0 = np.array([12.0, 6.0, 2.0, 0.0], np.float32)
  b = np.array([6.0, 3.0, 5.0, 4.0], np.float32)
  t = 0.04 * np.arange(1, 126)
  s = np.where(
      t < v0[:, None] / np.maximum(b[:, None], 1e-9),
      v0[:, None] * t - 0.5 * b[:, None] * t**2,
      v0[:, None] ** 2 / (2 * b[:, None]),
  )
  future = np.stack([s, 0 * s], -1).astype(np.float32)
  fitted = vmm.fit_controls(future, v0, np.zeros(4, np.float32))
  out = np.asarray(vmm.rollout(fitted, v0, 0.0))
  err = np.abs(out - future)
  assert err.max() < 0.15 and err.mean(1).max() < 0.06
  assert np.diff(out[..., 0], axis=-1).min() >= 0
