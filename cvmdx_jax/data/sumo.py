"""SUMO highway simulations exported as highD-format recordings (the embedded default data).

`make_recordings(cfg, out_dir)` runs one headless SUMO simulation per recording of
`sumo_plan.plans(cfg)` (PyPI `eclipse-sumo`, sublane model for continuous lateral motion,
0.04 s steps, seed `cfg.seed * 1000 + id`, the recording's own road and traffic),
`cfg.workers` processes at a time (SUMO and the CSV export of each), and writes
XX_tracks.csv, XX_tracksMeta.csv and XX_recordingMeta.csv for each, plus `plans.json`
(every recording's plan); `cvmdx_jax.data.highd` reads them like real highD recordings.
"""

import concurrent.futures
import multiprocessing
import signal
import sys
import tempfile
from pathlib import Path

import pandas as pd

from cvmdx_jax import constants
from cvmdx_jax.data import errors, sumo_export, sumo_network, sumo_plan

PLANS_FILE = "plans.json"

_FCD_COLUMNS = {
    "timestep_time": "time",
    "vehicle_id": "id",
    "vehicle_x": "x",
    "vehicle_y": "y",
    "vehicle_angle": "angle",
    "vehicle_type": "type",
    "vehicle_speed": "speed",
    "vehicle_acceleration": "acc",
}


def simulate(cfg, plan, work_dir: Path) -> pd.DataFrame:
  """Runs SUMO for one recording; returns its FCD rows (time, id, x, y, angle, type, speed,
  acc) in SUMO coordinates. Raises RuntimeError with SUMO's message when it fails."""
  recording_id = plan.recording_id
  name = f"rec{recording_id:02d}"
  net = sumo_network.write_network(cfg, plan.road, work_dir, name)
  routes = sumo_network.write_routes(cfg, plan, work_dir, name)
  fcd = work_dir / f"{name}.fcd.csv"
  command = [
      str(sumo_network.sumo_program("sumo")),
      "-n",
      str(net),
      "-r",
      str(routes),
      "--step-length",
      f"{constants.DT}",
      "--lateral-resolution",
      f"{cfg.lateral_resolution}",
      "--seed",
      str(cfg.seed * 1000 + recording_id),
      "--begin",
      "0",
      "--end",
      f"{cfg.warmup_s + plan.duration_s}",
      "--fcd-output",
      str(fcd),
      "--fcd-output.acceleration",
      "true",
      "--output.format",
      "csv",
      "--fcd-output.attributes",
      "x,y,angle,type,speed,acceleration",
      "--no-step-log",
      "true",
      "--no-warnings",
      "true",
      "--time-to-teleport",
      "-1",
      "--collision.action",
      "warn",
  ]
  result = sumo_network.run_program(command)
  if result.returncode != 0:
    raise RuntimeError(f"sumo failed for recording {recording_id}: {result.stderr[-2000:]}")
  frame = pd.read_csv(fcd, sep=";", usecols=list(_FCD_COLUMNS))
  fcd.unlink()
  frame = frame.rename(columns=_FCD_COLUMNS).dropna(subset=["id"])
  return frame[frame["time"] >= cfg.warmup_s].reset_index(drop=True)


def _exit_on_sigterm() -> None:
  """Initializer of a worker process: SIGTERM raises SystemExit, so that the
  `sumo_network.run_program` it is in kills its SUMO child on the way out."""
  signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))


def _simulate_and_export(cfg, plan, work_dir: Path, out_dir: Path) -> int:
  return sumo_export.export_recording(simulate(cfg, plan, work_dir), cfg, plan, out_dir)


def make_recordings(cfg, out_dir) -> dict:
  """Simulates and exports every recording of `sumo_plan.plans(cfg)` into `out_dir`.

  Returns:
    {recording id: number of rows in its tracks file}.
  """
  out_dir = Path(out_dir)
  try:
    sumo_network.sumo_program("sumo")
  except ImportError as e:  # before any process starts or anything is written
    raise errors.DataError(out_dir, str(e), column="source") from None
  plans = sumo_plan.plans(cfg)
  with tempfile.TemporaryDirectory(prefix="sumo_") as tmp:
    # Processes, not threads: the pandas export holds the GIL. Spawned: the parent may
    # already run JAX's threads, which a fork would copy half-way.
    with concurrent.futures.ProcessPoolExecutor(
        max(1, cfg.workers),
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_exit_on_sigterm,
    ) as pool:
      futures = [
          pool.submit(_simulate_and_export, cfg, plan, Path(tmp), out_dir)
          for plan in plans.values()
      ]
      try:
        rows = [f.result() for f in futures]
      except BaseException:  # a failed recording, Ctrl-C, SIGTERM (cli.run): stop the rest
        for future in futures:
          future.cancel()
        for worker in multiprocessing.active_children():
          worker.terminate()  # its SIGTERM handler kills its SUMO child
        raise
  sumo_plan.write_plans(plans, out_dir / PLANS_FILE)
  return dict(zip(plans, rows))
