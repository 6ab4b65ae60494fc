"""cVMD .mat reader on the shared fixtures, and the export/import round trip."""

import numpy as np
import pytest
import scipy.io

from cvmdx_jax import vmm
from cvmdx_jax.data import cvmd_mat


@pytest.fixture
def mat_dir(shared_dir):
  path = shared_dir / "fixtures" / "cvmd_mat"
  if not path.is_dir():
    pytest.skip("fixtures/cvmd_mat absent")
  return path


def test_load_fixture_frame_and_mask(mat_dir):
  s = cvmd_mat.load(mat_dir / "train")
  np.testing.assert_array_equal(s.label, [0, 1, 2])
  raw = scipy.io.loadmat(mat_dir / "train" / "class1" / "lcr0.mat")
  ego_last = np.array([raw["observed_data_x"][0, -1], raw["observed_data_y"][0, -1]])
  np.testing.assert_allclose(s.xi[1, 0, -1, :2], 0.0, atol=1e-5)
  np.testing.assert_allclose(s.future[1, :, 0], raw["predicted_x"][0] - ego_last[0], rtol=1e-5)
  np.testing.assert_allclose(s.future[1, :, 1], raw["predicted_y"][0] - ego_last[1], atol=1e-5)
  absent = (raw["observed_data_x"] == -1) & (raw["observed_data_y"] == -1)
  np.testing.assert_array_equal(s.mask[1], ~absent)
  assert not s.xi[1][absent].any()
  assert s.future[1, -1, 1] < -1.0 and s.future[2, -1, 1] > 0  # lcr right, lcl left


def test_fixture_controls_roll_out_to_future(mat_dir):
  s = cvmd_mat.load(mat_dir / "test")
  err = np.linalg.norm(np.asarray(vmm.rollout(s.controls, s.v0, s.psi0)) - s.future, axis=-1)
  # the example files' controls reproduce their future within 0.3 m over 5 s
  # (measured here: FDE <= 0.283 m, ADE <= 0.152 m)
  assert err[:, -1].max() <= 0.3 and err.mean(-1).max() <= 0.16


def test_export_import_round_trip(mat_dir, tmp_path):
  s = cvmd_mat.load(mat_dir / "test")
  paths = cvmd_mat.export(s, tmp_path / "test")
  assert sorted(p.parent.name for p in paths) == ["class0", "class1", "class2"]
  raw = scipy.io.loadmat(paths[0])
  assert raw["observed_data_x"][0, -1] == 0.0  # origin at the ego's last observed position
  assert np.all(raw["observed_data_x"][~s.mask[0]] == -1)
  back = cvmd_mat.load(tmp_path / "test")
  for name, value in s.as_dict().items():
    np.testing.assert_allclose(getattr(back, name), value, atol=1e-6, err_msg=name)
