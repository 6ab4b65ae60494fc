"""Runs the toy task through `cvmdx_jax.train.loop.train` in its own process.

Used by the tests for what needs a fresh process: several CPU devices (XLA_FLAGS must be
set before jax is imported) and being killed with SIGKILL. Prints one line
"epoch <k>" per finished epoch and finally one JSON line {"devices", "params", "loss"}.
Run: PYTHONPATH=. python tests/train/toy_job.py --workdir=DIR [--epochs=..].
"""

import argparse
import json
import sys
import time

import jax

from cvmdx_jax.train import loop
from tests.train import toy


def main() -> int:
  p = argparse.ArgumentParser()
  p.add_argument("--workdir", required=True)
  p.add_argument("--epochs", type=int, default=3)
  p.add_argument("--batch_size", type=int, default=8)
  p.add_argument("--m", type=int, default=36)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--sleep", type=float, default=0.0, help="seconds to idle after each epoch")
  a = p.parse_args()
  init_fn, step_fn = toy.make_task()

  def epoch_end(state, epoch):
    print(f"epoch {epoch}", flush=True)
    time.sleep(a.sleep)
    return {}

  try:
    state = loop.train(workdir=a.workdir, init_fn=init_fn, step_fn=step_fn,
                       data=toy.make_data(a.m), batch_size=a.batch_size,
                       num_epochs=a.epochs, seed=a.seed, fingerprint={"task": "toy"},
                       epoch_end_fn=epoch_end)
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  with open(f"{a.workdir}/metrics.jsonl") as f:
    last = json.loads(f.read().splitlines()[-1])
  print(json.dumps({"devices": jax.device_count(), "params": toy.flat_params(state).tolist(),
                    "loss": last["loss"]}), flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())
