"""Per-recording statistics of a SUMO dataset (road, traffic, speeds, lane changes).

  .venv/bin/python experiments/recording_stats.py --data_dir=data/sumo

Reads <data_dir>/recordings (XX_*.csv and plans.json, written by make_dataset.py), prints a
markdown table with one row per recording and writes <data_dir>/recording_stats.json.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

from pathlib import Path

from absl import app, flags

from cvmdx_jax.data import sumo_stats
from cvmdx_jax.storage import atomic

_DATA_DIR = flags.DEFINE_string("data_dir", "data/sumo", "Dataset directory (make_dataset.py).")
cli.input_dirs("data_dir")


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  rows = sumo_stats.sumo_table(Path(_DATA_DIR.value) / "recordings")
  columns = list(rows[0])
  lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
  for row in rows:
    lines.append(
        "| "
        + " | ".join("-".join(map(str, v)) if isinstance(v, list) else str(v) for v in row.values())
        + " |"
    )
  print("\n".join(lines))
  atomic.write_json(Path(_DATA_DIR.value) / "recording_stats.json", rows)


if __name__ == "__main__":
  cli.run(main)
