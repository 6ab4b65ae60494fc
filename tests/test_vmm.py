"""VMM rollout against a numpy loop, closed forms and the cVMD example files."""

import glob
import math

import jax
import numpy as np
import scipy.io

from cvmdx_jax import vmm


def numpy_rollout(controls, v0, psi0, dt=0.04):
  x = y = 0.0
  v, psi = v0, psi0
  out = []
  for a, w in controls:
    x += v * math.cos(psi) * dt + (a * math.cos(psi) - w * v * math.sin(psi)) * dt**2 / 2
    y += v * math.sin(psi) * dt + (a * math.sin(psi) + w * v * math.cos(psi)) * dt**2 / 2
    v += a * dt
    psi += w * dt
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
      np.testing.assert_allclose(out[i, j], numpy_rollout(controls[i, j], v0[i, j], psi0[i, j]),
                                 atol=2e-3)
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
  np.testing.assert_allclose(np.linalg.norm(out - [-r * math.sin(psi0), r * math.cos(psi0)],
                                            axis=-1), r, rtol=1e-3)


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
