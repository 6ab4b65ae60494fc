"""SUMO highway simulations exported as highD-format recordings (the embedded default data).

`make_recordings(cfg, out_dir)` runs one headless SUMO simulation per recording id (PyPI
`eclipse-sumo`, sublane model for continuous lateral motion, 0.04 s steps, seed
`cfg.seed * 1000 + id`), `cfg.workers` at a time, and writes XX_tracks.csv,
XX_tracksMeta.csv and XX_recordingMeta.csv for each; `cvmdx_jax.data.highd` reads them
like real highD recordings.
"""

import concurrent.futures
import subprocess
import tempfile
from pathlib import Path

import pandas as pd
import sumo as sumo_pkg

from cvmdx_jax import constants
from cvmdx_jax.data import sumo_export, sumo_network

_FCD_COLUMNS = {"timestep_time": "time", "vehicle_id": "id", "vehicle_x": "x",
                "vehicle_y": "y", "vehicle_angle": "angle", "vehicle_type": "type",
                "vehicle_speed": "speed", "vehicle_acceleration": "acc"}


def simulate(cfg, recording_id: int, net: Path, work_dir: Path) -> pd.DataFrame:
  """Runs SUMO for one recording; returns its FCD rows (time, id, x, y, angle, type, speed,
  acc) in SUMO coordinates. Raises RuntimeError with SUMO's message when it fails."""
  name = f"rec{recording_id:02d}"
  routes = sumo_network.write_routes(cfg, work_dir, name)
  fcd = work_dir / f"{name}.fcd.csv"
  command = [
      str(Path(sumo_pkg.SUMO_HOME) / "bin" / "sumo"), "-n", str(net), "-r", str(routes),
      "--step-length", f"{constants.DT}", "--lateral-resolution", f"{cfg.lateral_resolution}",
      "--seed", str(cfg.seed * 1000 + recording_id), "--begin", "0",
      "--end", f"{cfg.warmup_s + cfg.duration_s}", "--fcd-output", str(fcd),
      "--fcd-output.acceleration", "true", "--output.format", "csv",
      "--fcd-output.attributes", "x,y,angle,type,speed,acceleration",
      "--no-step-log", "true", "--no-warnings", "true",
      "--time-to-teleport", "-1", "--collision.action", "warn"]
  result = subprocess.run(command, capture_output=True, text=True)
  if result.returncode != 0:
    raise RuntimeError(f"sumo failed for recording {recording_id}: {result.stderr[-2000:]}")
  frame = pd.read_csv(fcd, sep=";", usecols=list(_FCD_COLUMNS))
  fcd.unlink()
  frame = frame.rename(columns=_FCD_COLUMNS).dropna(subset=["id"])
  return frame[frame["time"] >= cfg.warmup_s].reset_index(drop=True)


def make_recordings(cfg, out_dir) -> dict:
  """Simulates and exports recordings 1..cfg.num_recordings into `out_dir`.

  Returns:
    {recording id: number of rows in its tracks file}.
  """
  out_dir = Path(out_dir)
  ids = list(range(1, cfg.num_recordings + 1))
  with tempfile.TemporaryDirectory(prefix="sumo_") as tmp:
    work_dir = Path(tmp)
    net = sumo_network.write_network(cfg, work_dir)

    def one(recording_id):
      fcd = simulate(cfg, recording_id, net, work_dir)
      return sumo_export.export_recording(fcd, cfg, recording_id, out_dir)

    with concurrent.futures.ThreadPoolExecutor(max(1, cfg.workers)) as pool:
      rows = list(pool.map(one, ids))
  return dict(zip(ids, rows))
