"""A report as plain data (`Report`) and its files (`write`): metrics<suffix>.json,
results<suffix>.md, predictions<suffix>.npz (`prediction_arrays`) and the PNG figures,
written as one group (`checksums.write_all`: all new or all old)."""

import dataclasses
from pathlib import Path

import numpy as np

from cvmdx_jax.storage import atomic, checksums


@dataclasses.dataclass(frozen=True)
class Report:
  """One split's report as plain data: `results` ({method: {subset: {metric}}}), `meta`,
  the markdown `tables`, the `arrays` of predictions<suffix>.npz, and `pngs` ({file stem:
  PNG bytes}; `stale`: class-figure stems this report lacks)."""

  results: dict
  meta: dict
  tables: str
  arrays: dict
  pngs: dict
  stale: tuple


def prediction_arrays(scenarios, out, errors: dict) -> dict:
  """The arrays of `predictions<suffix>.npz`, one row per evaluated scenario (M):
  `recording_id`, `track_id`, `frame`, `label` (M,) int (the scenario's provenance, as in
  the dataset); `mean` (M, 125, 2) m; `hypotheses` (M, K, 125, 2) m and `probs` (M, K) (0 =
  unused slot); `q`, `delta`, `out_of_distribution` (M,); and `<method>_<metric>` (M,) for
  every method and metric of `errors` (per-scenario values on these M scenarios, the energy
  scores among them; best of K: ade / fde are minADE_K / minFDE_K; NaN where a metric does
  not apply, e.g. target_lane_hit on keep-lane scenarios)."""
  arrays = {
      name: np.asarray(getattr(scenarios, name))
      for name in ("recording_id", "track_id", "frame", "label")
  }
  hyp = out.hypotheses
  arrays.update(
      mean=out.mean,
      hypotheses=hyp.means,
      probs=hyp.probs,
      q=out.q,
      delta=out.delta,
      out_of_distribution=out.out_of_distribution,
  )
  for method, per in errors.items():
    arrays.update(
        {
            f"{method}_{metric}": np.ma.filled(np.ma.asarray(value, np.float64), np.nan)
            for metric, value in per.items()
        }
    )
  return {name: np.asarray(value) for name, value in arrays.items()}


def write(report: Report, workdir, suffix: str = "") -> None:
  """Writes a `Report` into `workdir` (created) as one group; a class figure of the
  previous report of this suffix that this one lacks is removed."""
  workdir = Path(workdir)
  workdir.mkdir(parents=True, exist_ok=True)
  metrics = atomic.json_text({**report.results, "_meta": report.meta}).encode()
  checksums.write_all(
      {  # metrics.json first: renamed last
          workdir / f"metrics{suffix}.json": metrics,
          workdir / f"results{suffix}.md": report.tables.encode(),
          workdir / f"predictions{suffix}.npz": checksums.npz_bytes(**report.arrays),
          **{workdir / f"{stem}{suffix}.png": png for stem, png in report.pngs.items()},
      }
  )
  for stem in report.stale:
    (workdir / f"{stem}{suffix}.png").unlink(missing_ok=True)
