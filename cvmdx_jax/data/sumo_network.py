"""SUMO inputs for the default dataset: a straight two-carriageway highway and its traffic.

Network (SUMO coordinates, y up): eastbound edge `E` on y = -median/2 and westbound edge `W`
on y = +median/2, each `lanes` lanes wide, spread to the right of their direction, so the
westbound lanes lie north (upper image half, highD drivingDirection 1, toward -x) and the
eastbound lanes south (drivingDirection 2, toward +x). Traffic: Poisson flows per direction
from a mix of car and truck types with spread desired speeds and lane-change eagerness.
"""

import subprocess
from pathlib import Path

import numpy as np
import sumo

# name, class, probability, length m, width m, max speed m/s, speedFactor distribution,
# lcSpeedGain, lcKeepRight, maxSpeedLat m/s
VEHICLE_TYPES = (
    ("car_eager", "Car", 0.25, 4.6, 1.9, 55.0, "normc(1.25,0.12,0.9,1.6)", 4.0, 0.5, 1.3),
    ("car_normal", "Car", 0.35, 4.8, 1.9, 50.0, "normc(1.05,0.1,0.8,1.4)", 1.5, 1.0, 1.0),
    ("car_calm", "Car", 0.2, 4.4, 1.8, 45.0, "normc(0.9,0.08,0.7,1.2)", 0.7, 2.0, 0.8),
    ("truck", "Truck", 0.12, 16.0, 2.55, 25.0, "normc(0.75,0.04,0.6,0.85)", 0.5, 3.0, 0.6),
    ("truck_short", "Truck", 0.08, 12.0, 2.5, 27.0, "normc(0.8,0.05,0.65,0.9)", 0.8, 2.0, 0.7),
)


def vehicle_dims() -> dict:
  """type name -> (class, length m, width m)."""
  return {t[0]: (t[1], t[3], t[4]) for t in VEHICLE_TYPES}


def lane_markings(cfg) -> tuple[np.ndarray, np.ndarray]:
  """Marking y positions in SUMO coordinates (y up), each (lanes + 1,) ascending in y:
  (north carriageway = westbound, south carriageway = eastbound)."""
  half, width, n = cfg.median_m / 2, cfg.lane_width_m, cfg.lanes
  north = half + width * np.arange(n + 1)
  south = -half - width * np.arange(n, -1, -1)
  return north, south


def write_network(cfg, work_dir: Path) -> Path:
  """Writes plain nodes/edges and runs netconvert; returns the .net.xml path."""
  work_dir.mkdir(parents=True, exist_ok=True)
  half, length = cfg.median_m / 2, cfg.road_length_m
  nodes = work_dir / "highway.nod.xml"
  edges = work_dir / "highway.edg.xml"
  net = work_dir / "highway.net.xml"
  nodes.write_text(
      "<nodes>\n"
      f'  <node id="e0" x="0" y="{-half}"/>\n  <node id="e1" x="{length}" y="{-half}"/>\n'
      f'  <node id="w0" x="{length}" y="{half}"/>\n  <node id="w1" x="0" y="{half}"/>\n'
      "</nodes>\n")
  edges.write_text(
      "<edges>\n"
      f'  <edge id="E" from="e0" to="e1" numLanes="{cfg.lanes}" speed="{cfg.speed_limit_ms}" '
      f'width="{cfg.lane_width_m}" spreadType="right"/>\n'
      f'  <edge id="W" from="w0" to="w1" numLanes="{cfg.lanes}" speed="{cfg.speed_limit_ms}" '
      f'width="{cfg.lane_width_m}" spreadType="right"/>\n'
      "</edges>\n")
  netconvert = Path(sumo.SUMO_HOME) / "bin" / "netconvert"
  subprocess.run([str(netconvert), "-n", str(nodes), "-e", str(edges), "-o", str(net),
                  "--no-turnarounds", "true", "--no-warnings", "true"],
                 check=True, capture_output=True)
  return net


def write_routes(cfg, work_dir: Path, name: str) -> Path:
  """Vehicle types and Poisson flows on both carriageways for the whole simulated time."""
  lines = ["<routes>", '  <vTypeDistribution id="mix">']
  for (tid, vclass, prob, length, width, vmax, factor, gain, keep_right, lat) in VEHICLE_TYPES:
    sumo_class = "truck" if vclass == "Truck" else "passenger"
    lines.append(
        f'    <vType id="{tid}" vClass="{sumo_class}" probability="{prob}" length="{length}" '
        f'width="{width}" maxSpeed="{vmax}" speedFactor="{factor}" lcSpeedGain="{gain}" '
        f'lcKeepRight="{keep_right}" maxSpeedLat="{lat}" latAlignment="center" '
        f'lcAssertive="1.5" sigma="0.3"/>')
  lines.append("  </vTypeDistribution>")
  end = cfg.warmup_s + cfg.duration_s
  rate = cfg.flow_veh_per_hour / 3600.0
  for edge in ("E", "W"):
    lines.append(
        f'  <flow id="f{edge}" type="mix" begin="0" end="{end}" period="exp({rate:.5f})" '
        f'from="{edge}" to="{edge}" departLane="random" departSpeed="desired" '
        'departPosLat="center"/>')
  lines.append("</routes>")
  path = work_dir / f"{name}.rou.xml"
  path.write_text("\n".join(lines) + "\n")
  return path
