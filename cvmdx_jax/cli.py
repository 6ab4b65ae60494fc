"""Running the absl entry points in `experiments/`."""

import sys
from pathlib import Path

from absl import app


def run(main) -> None:
  """`app.run(main)`; bad input (ValueError, including DataError, or FileNotFoundError)
  prints `<script>: error: <message>` to stderr and exits with status 2."""
  try:
    app.run(main)
  except (ValueError, FileNotFoundError) as e:
    print(f"{Path(sys.argv[0]).stem}: error: {e}", file=sys.stderr)
    sys.exit(2)
