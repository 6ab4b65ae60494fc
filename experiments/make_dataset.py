"""Builds the dataset cache and prints / saves its summary.

  .venv/bin/python experiments/make_dataset.py --config=configs/dataset.py \
      --data_dir=data/sumo                      # presets: configs/dataset.py:small, :tiny
  ... --config.source=highd --config.highd_dir=/path/to/highD/data --data_dir=data/highd
  ... --config.source=cvmd_mat --config.mat_dir=/path/to/mat --data_dir=data/mat

Writes <data_dir>/cache/{train,val,test[,test_ood]}.npz + metadata.json and
<data_dir>/summary.json (per-recording statistics: experiments/recording_stats.py); exits
non-zero with a message naming file, row and column on bad input.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import json
import time
from pathlib import Path

from absl import app, flags
from ml_collections import config_flags

from cvmdx_jax.data import dataset, summary
from cvmdx_jax.storage import atomic

_CONFIG = config_flags.DEFINE_config_file(
    "config", "configs/dataset.py", "Dataset config.", lock_config=True
)
_DATA_DIR = flags.DEFINE_string("data_dir", "data/sumo", "Output directory.")
cli.output_dirs("data_dir")
cli.typed_config("config", dataset.checked_config)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments {argv[1:]}")
  start = time.time()
  splits = dataset.build(_CONFIG.value, _DATA_DIR.value)
  result = {
      "dataset_id": dataset.dataset_id(_DATA_DIR.value),
      "seconds": round(time.time() - start, 1),
      "splits": summary.summarize(splits),
  }
  text = json.dumps(result, indent=1)
  print(text)
  atomic.write_text(Path(_DATA_DIR.value) / "summary.json", text + "\n")


if __name__ == "__main__":
  cli.run(main)
