"""cVMD / cVMDx `.mat` scenario folders: `split_dir/class{0,1,2}/*.mat` <-> `Scenarios`.

Per file: observed_data_{x,y,vx,vy} (9, 75) with absent entries = -1, predicted_{x,y,ax,dpsi}
(1, 125), psi_0 and v0 (1, 1), scenario_type, data_keys. The class comes from the folder.

Reading moves the observation into our frame: origin at the ego's last observed position,
so xi x, y = observed - ego(t0) and future = predicted_x/y - ego(t0); absent entries (x and y
both -1) are masked and zeroed. Exporting writes that same frame: observed x, y relative to
the ego at the last observed step (ego x = y = 0 there) and predicted_x/y relative to it,
which is what the cVMDx evaluation assumes; absent = -1.
"""

from pathlib import Path

import numpy as np
import scipy.io

from cvmdx_jax import constants
from cvmdx_jax.data import scenarios as scenarios_lib
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.storage import atomic

_OBS_KEYS = ("observed_data_x", "observed_data_y", "observed_data_vx", "observed_data_vy")
_SCENARIO_TYPES = ("keep_lane", "lane_change_right", "lane_change_left")
_KEY_WIDTH = max(len(k) for k in constants.VEHICLE_SLOTS) + 1


def _field(mat: dict, path: Path, key: str, shape: tuple) -> np.ndarray:
  if key not in mat:
    raise DataError(path, "missing variable", column=key)
  value = np.asarray(mat[key], np.float64)
  if value.shape != shape:
    raise DataError(path, f"shape {value.shape}, expected {shape}", column=key)
  if not np.all(np.isfinite(value)):
    raise DataError(path, "NaN or infinite values", column=key)
  return value


def _read_file(path: Path, label: int) -> dict:
  try:
    mat = scipy.io.loadmat(path)
  except (OSError, ValueError) as err:
    raise DataError(path, f"unreadable .mat file ({err})") from err
  obs_shape = (constants.NUM_VEHICLES, constants.T_OBS)
  obs = np.stack([_field(mat, path, k, obs_shape) for k in _OBS_KEYS], -1)  # (9, 75, 4)
  pred = {
      k: _field(mat, path, f"predicted_{k}", (1, constants.T_PRED))[0]
      for k in ("x", "y", "ax", "dpsi")
  }
  kind = str(np.asarray(mat.get("scenario_type", [""])).ravel()[0]).strip()
  if kind and kind != _SCENARIO_TYPES[label]:
    raise DataError(path, f"scenario_type '{kind}' in folder class{label}", column="scenario_type")
  mask = ~((obs[..., 0] == -1) & (obs[..., 1] == -1))
  if not mask[0, -1]:
    raise DataError(path, "the ego is absent at the last observed step", column="observed_data_x")
  origin = obs[0, -1, :2]
  xi = obs.copy()
  xi[..., :2] -= origin
  xi *= mask[..., None]
  return {
      "xi": xi,
      "mask": mask,
      "future": np.stack([pred["x"], pred["y"]], -1) - origin,
      "controls": np.stack([pred["ax"], pred["dpsi"]], -1),
      "v0": _field(mat, path, "v0", (1, 1))[0, 0],
      "psi0": _field(mat, path, "psi_0", (1, 1))[0, 0],
      "label": label,
  }


def load(split_dir) -> scenarios_lib.Scenarios:
  """Reads `split_dir/class{0,1,2}/*.mat` (sorted by class, then file name)."""
  split_dir = Path(split_dir)
  records = [
      _read_file(path, label)
      for label in range(constants.NUM_CLASSES)
      for path in sorted((split_dir / f"class{label}").glob("*.mat"))
  ]
  if not records:
    raise DataError(split_dir, "empty selection: no class{0,1,2}/*.mat files")
  return scenarios_lib.from_arrays(**{k: np.stack([r[k] for r in records]) for k in records[0]})


def export(scenarios: scenarios_lib.Scenarios, split_dir) -> list:
  """Writes one .mat per scenario to `split_dir/class{label}/{index:06d}.mat`.

  Returns:
    The written paths. Each file is written to a temporary name and renamed.
  """
  split_dir = Path(split_dir)
  s = {k: np.asarray(v) for k, v in scenarios.validate().as_dict().items()}
  keys = np.array([k.ljust(_KEY_WIDTH) for k in constants.VEHICLE_SLOTS])
  paths = []
  for i in range(len(scenarios)):
    label = int(s["label"][i])
    obs = np.where(s["mask"][i][..., None], s["xi"][i].astype(np.float64), -1.0)
    mat = {k: obs[..., j] for j, k in enumerate(_OBS_KEYS)}
    future, controls = s["future"][i].astype(np.float64), s["controls"][i].astype(np.float64)
    mat.update(
        predicted_x=future[None, :, 0],
        predicted_y=future[None, :, 1],
        predicted_ax=controls[None, :, 0],
        predicted_dpsi=controls[None, :, 1],
        psi_0=np.array([[s["psi0"][i]]], np.float64),
        v0=np.array([[s["v0"][i]]], np.float64),
        scenario_type=np.array([_SCENARIO_TYPES[label]]),
        data_keys=keys,
    )
    path = split_dir / f"class{label}" / f"{i:06d}.mat"
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_mat(path, mat)
    paths.append(path)
  return paths
