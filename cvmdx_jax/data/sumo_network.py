"""SUMO inputs of one recording: a straight two-carriageway highway and its traffic.

Network (SUMO coordinates, y up): eastbound edge `E` on y = -median/2 and westbound edge `W`
on y = +median/2, each `road.lanes` lanes of `road.lane_width_m`, spread to the right of their
direction, so the westbound lanes lie north (upper image half, highD drivingDirection 1,
toward -x) and the eastbound lanes south (drivingDirection 2, toward +x). SUMO lane index 0
is the rightmost lane of its direction. Traffic: Poisson flows per direction from the
recording's vTypes (`sumo_plan.RecordingPlan`).
"""

import signal
import subprocess
import threading
from pathlib import Path

import numpy as np

# DriverType field -> SUMO vType attribute, for the car-following and lane-change parameters.
_VTYPE_ATTRIBUTES = (
    ("accel", "accel"),
    ("decel", "decel"),
    ("sigma", "sigma"),
    ("tau", "tau"),
    ("lc_speed_gain", "lcSpeedGain"),
    ("lc_keep_right", "lcKeepRight"),
    ("max_speed_lat", "maxSpeedLat"),
    ("lc_accel_lat", "lcAccelLat"),
)


_HELD = (signal.SIGINT, signal.SIGTERM)


def _start(command: list[str]) -> subprocess.Popen:
  """`Popen(command)` (text pipes) with SIGINT and SIGTERM held while it starts: a signal's
  exception raised inside Popen's constructor, after the child's exec, would lose the child
  (it would outlive this process, holding its pipes). A held signal kills the child and is
  then raised again, reaching the handler it was meant for."""
  held, previous, child = [], {}, None
  if threading.current_thread() is threading.main_thread():
    for number in _HELD:
      previous[number] = signal.signal(number, lambda signum, frame: held.append(signum))
  try:
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
  finally:
    for number, handler in previous.items():
      signal.signal(number, signal.SIG_DFL if handler is None else handler)
    if held and child is not None:
      child.kill()
      child.communicate()
    if held:
      signal.raise_signal(held[0])
  return child


def run_program(command: list[str], check: bool = False) -> subprocess.CompletedProcess:
  """`subprocess.run(command, capture_output=True, text=True, check=check)`, whose child is
  also killed when SIGINT or SIGTERM arrives while it starts (`_start`)."""
  with _start(command) as child:
    try:
      out, err = child.communicate()
    except BaseException:  # Ctrl-C, SIGTERM: the child goes first
      child.kill()
      raise
  if check and child.returncode:
    raise subprocess.CalledProcessError(child.returncode, command, out, err)
  return subprocess.CompletedProcess(command, child.returncode, out, err)


def sumo_program(name: str) -> Path:
  """SUMO's program `name` ('sumo', 'netconvert') in the eclipse-sumo package, imported here
  and not with the module, so that reading, training and evaluating need no SUMO.

  Raises:
    ImportError: eclipse-sumo is not installed; the message says how to install it.
  """
  try:
    import sumo  # pylint: disable=import-outside-toplevel
  except ImportError:
    raise ImportError(
        "the SUMO source needs SUMO's programs: install eclipse-sumo (`make "
        "install` does; pip install eclipse-sumo), or read highD "
        "(source='highd')"
    ) from None
  return Path(sumo.SUMO_HOME) / "bin" / name


def vehicle_dims(plan) -> dict:
  """vType id -> (highD class, length m, width m) of the recording's types."""
  return {t.name: (t.vclass, t.length_m, t.width_m) for t in plan.types}


def lane_markings(road, median_m: float) -> tuple[np.ndarray, np.ndarray]:
  """Marking y positions in SUMO coordinates (y up), each (lanes + 1,) ascending in y:
  (north carriageway = westbound, south carriageway = eastbound)."""
  half, width, n = median_m / 2, road.lane_width_m, road.lanes
  north = half + width * np.arange(n + 1)
  south = -half - width * np.arange(n, -1, -1)
  return north, south


def write_network(cfg, road, work_dir: Path, name: str = "highway") -> Path:
  """Writes plain nodes/edges of `road` and runs netconvert; returns the .net.xml path."""
  work_dir.mkdir(parents=True, exist_ok=True)
  half, length = cfg.median_m / 2, cfg.road_length_m
  nodes = work_dir / f"{name}.nod.xml"
  edges = work_dir / f"{name}.edg.xml"
  net = work_dir / f"{name}.net.xml"
  nodes.write_text(
      "<nodes>\n"
      f'  <node id="e0" x="0" y="{-half}"/>\n  <node id="e1" x="{length}" y="{-half}"/>\n'
      f'  <node id="w0" x="{length}" y="{half}"/>\n  <node id="w1" x="0" y="{half}"/>\n'
      "</nodes>\n"
  )
  lanes = (
      f'numLanes="{road.lanes}" speed="{road.speed_limit_ms:.4f}" '
      f'width="{road.lane_width_m}" spreadType="right"'
  )
  edges.write_text(
      "<edges>\n"
      f'  <edge id="E" from="e0" to="e1" {lanes}/>\n'
      f'  <edge id="W" from="w0" to="w1" {lanes}/>\n'
      "</edges>\n"
  )
  run_program(
      [
          str(sumo_program("netconvert")),
          "-n",
          str(nodes),
          "-e",
          str(edges),
          "-o",
          str(net),
          "--no-turnarounds",
          "true",
          "--no-warnings",
          "true",
      ],
      check=True,
  )
  return net


def _vtype(t, car_following: str) -> str:
  sumo_class = "truck" if t.vclass == "Truck" else "passenger"
  attributes = [
      f'id="{t.name}"',
      f'vClass="{sumo_class}"',
      f'probability="{t.probability:.4f}"',
      f'length="{t.length_m:.2f}"',
      f'width="{t.width_m:.2f}"',
      f'carFollowModel="{car_following}"',
      f'speedFactor="normc({t.speed_factor:.3f},{t.speed_dev:.3f},0.6,1.5)"',
  ]
  if t.desired_max_speed_ms:
    attributes.append(f'desiredMaxSpeed="{t.desired_max_speed_ms:.3f}"')
  attributes += [f'{attr}="{getattr(t, field):.3f}"' for field, attr in _VTYPE_ATTRIBUTES]
  return f'    <vType {" ".join(attributes)} latAlignment="center" lcAssertive="1.5"/>'


def write_routes(cfg, plan, work_dir: Path, name: str) -> Path:
  """The recording's vTypes and Poisson flows on both carriageways for the simulated time."""
  lines = ["<routes>", '  <vTypeDistribution id="mix">']
  lines += [_vtype(t, plan.car_following) for t in plan.types]
  lines.append("  </vTypeDistribution>")
  end = cfg.warmup_s + plan.duration_s
  rate = plan.flow_veh_per_hour / 3600.0
  for edge in ("E", "W"):
    lines.append(
        f'  <flow id="f{edge}" type="mix" begin="0" end="{end}" period="exp({rate:.5f})" '
        f'from="{edge}" to="{edge}" departLane="random" departSpeed="desired" '
        'departPosLat="center"/>'
    )
  lines.append("</routes>")
  path = work_dir / f"{name}.rou.xml"
  path.write_text("\n".join(lines) + "\n")
  return path
