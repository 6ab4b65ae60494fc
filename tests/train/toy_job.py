"""Runs a task through `cvmdx_jax.train.loop.train` in its own process.

Tasks (`--task`): "toy" (the MLP of toy.py), "diffusion" and "tokenizer" (the real
step functions with their `:tiny` configs on synthetic data).

Used by the tests for what needs a fresh process: several CPU devices (XLA_FLAGS must be
set before jax is imported), being killed with SIGKILL, and several processes of one
`jax.distributed` run (JAX_NUM_PROCESSES etc., see `cvmdx_jax.sharding`). Prints one line
"epoch <k>" per finished epoch and finally one JSON line {"devices", "process", "params",
"loss"} ("loss" from metrics.jsonl, which process 0 writes).
Run: PYTHONPATH=. python tests/train/toy_job.py --workdir=DIR [--epochs=..].
"""

import argparse
import json
import sys
import time

import jax
import numpy as np

from cvmdx_jax import sharding
from cvmdx_jax.train import preemption
from tests.train import toy


def task(name: str, m: int):
  """(init_fn, step_fn, data) of a task."""
  if name == "toy":
    return (*toy.make_task(), toy.make_data(m))
  rng = np.random.default_rng(0)
  if name == "diffusion":
    from configs import diffusion as diffusion_config
    from cvmdx_jax.config.runs import DiffusionRunConfig
    from cvmdx_jax.train import diffusion

    config = DiffusionRunConfig.from_config(diffusion_config.get_config("tiny")).with_tokens(4)
    _, init_fn, step_fn = diffusion.init_and_step(config, total_steps=100)
    data = {
        "x0": rng.uniform(-1, 1, (m, 125, 2)).astype(np.float32),
        "q": rng.integers(0, 4, m).astype(np.int32),
    }
    return init_fn, step_fn, data
  from configs import tokenizer as tokenizer_config
  from cvmdx_jax.config.runs import TokenizerRunConfig
  from cvmdx_jax.models import tokenizer as tokenizer_lib
  from cvmdx_jax.train import tokenizer

  run = TokenizerRunConfig.from_config(tokenizer_config.get_config("tiny"))
  model_cfg, tx = run.model, tokenizer.optimizer(run.train)
  graphdef = tokenizer_lib.make_graphdef(model_cfg)
  data = {
      "xi": rng.normal(0, [20, 2, 30, 0.3], (m, 9, 75, 4)).astype(np.float32),
      "mask": rng.uniform(size=(m, 9, 75)) < 0.8,
      "label": rng.integers(0, 3, m),
  }
  return (
      tokenizer.make_init_fn(model_cfg, tx),
      tokenizer.make_step_fn(graphdef, model_cfg, tx),
      data,
  )


def main() -> int:
  p = argparse.ArgumentParser()
  p.add_argument("--workdir", required=True)
  p.add_argument("--epochs", type=int, default=3)
  p.add_argument("--batch_size", type=int, default=8)
  p.add_argument("--m", type=int, default=36)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--task", default="toy", choices=("toy", "diffusion", "tokenizer"))
  p.add_argument("--sleep", type=float, default=0.0, help="seconds to idle after each epoch")
  a = p.parse_args()
  sharding.initialize_distributed()
  init_fn, step_fn, data = task(a.task, a.m)

  def epoch_end(state, epoch):
    print(f"epoch {epoch}", flush=True)
    time.sleep(a.sleep)
    return {}

  try:
    state = toy.train(
        workdir=a.workdir,
        init_fn=init_fn,
        step_fn=step_fn,
        data=data,
        batch_size=a.batch_size,
        num_epochs=a.epochs,
        seed=a.seed,
        fingerprint={"task": "toy"},
        epoch_end_fn=epoch_end,
    )
  except ValueError as e:
    print(f"error: {e}", file=sys.stderr)
    return 2
  except preemption.Stopped as e:
    print(f"stopped: {e.message}", file=sys.stderr)
    return e.code
  loss = None
  if sharding.is_primary():
    with open(f"{a.workdir}/metrics.jsonl") as f:
      loss = json.loads(f.read().splitlines()[-1])["loss"]
  print(
      json.dumps(
          {
              "devices": jax.device_count(),
              "process": jax.process_index(),
              "params": toy.flat_params(state).tolist(),
              "loss": loss,
          }
      ),
      flush=True,
  )
  return 0


if __name__ == "__main__":
  sys.exit(main())
