"""Latency of cVMDx inside a driving stack, side by side in one run: all vehicles of one
frame per call, and the first call of the exported artefact against the package's.

  .venv/bin/python experiments/benchmark_stack.py --tokenizer_dir=runs/demo/tokenizer \\
      --diffusion_dir=runs/demo/student_progressive_1 --data_dir=runs/demo/data

1. A frame of --vehicles vehicles (the first scenarios of the test split: a vehicle's input
   is its 3 s of history and its neighbours', whatever the frame) predicted by one
   `Predictor` call (chunk = the frame) with each of --samples (default the paper's 9 and
   the demo's 64): first call (trace + compile + run), then median and p90 of --calls warm
   calls, end to end (input checks, transfers, numpy outputs). Once per CPU device count
   of --host_devices (`sharding.use_host_devices`: the frame's vehicles split over them),
   each in a fresh process, one after the other: the ratio of medians against the first.
2. Where the time goes for the first of --samples, each part jitted alone on the same
   frame: tokeniser (+ ego features), sampler (the U-Net evaluations), vehicle motion model,
   hypotheses (medians of --calls calls; the sum differs from the whole by fusion).
3. First call in a fresh process, each the median of --first_call_runs processes: the
   package (import, `Predictor.load`, first call = trace + compile + run) against the
   artefact of experiments/export.py (import jax, read + deserialise, first call = compile
   + run); both for the first of --samples.

Prints a table and writes it with the machine (CPU model, cores, load average) to --out
(JSON) if given.
"""

from cvmdx_jax import cli  # first: a signal during the imports below is one line

# isort: split

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from absl import flags

from cvmdx_jax import ego_motion, sharding, vmm
from cvmdx_jax.data import dataset
from cvmdx_jax.errors import UserError
from cvmdx_jax.inference import export
from cvmdx_jax.inference.predictor import Predictor
from cvmdx_jax.multimodal import fit_hypotheses
from cvmdx_jax.storage import atomic

_TOKENIZER = flags.DEFINE_string("tokenizer_dir", None, "Tokeniser run directory.")
_DIFFUSION = flags.DEFINE_string("diffusion_dir", None, "Diffusion or distilled run directory.")
_DATA = flags.DEFINE_string("data_dir", None, "Dataset directory (its test split is read).")
_VEHICLES = flags.DEFINE_integer("vehicles", 30, "Vehicles in the frame.", lower_bound=1)
_CALLS = flags.DEFINE_integer("calls", 50, "Warm calls timed.", lower_bound=1)
_SAMPLES = flags.DEFINE_list("samples", ["9", "64"], "Samples per vehicle, one row each.")
_RUNS = flags.DEFINE_integer(
    "first_call_runs",
    3,
    "Fresh processes per first-call timing " "(0 = skip part 3).",
    lower_bound=0,
)
_OUT = flags.DEFINE_string("out", None, "JSON file of the results (none: print only).")
_HOST = flags.DEFINE_list("host_devices", ["1", "2"], "CPU device counts of part 1, side by side.")
_CHILD = flags.DEFINE_enum(
    "child",
    None,
    ["package", "exported", "frame"],
    "Internal: time one first call (package, exported) or part 1 on the first of "
    "--host_devices (frame) in this process and print it as JSON.",
)
_EXPORT_DIR = flags.DEFINE_string("export_dir", None, "Internal: the artefacts of --child.")
flags.mark_flags_as_required(["tokenizer_dir", "diffusion_dir", "data_dir"])
cli.input_dirs("tokenizer_dir", "diffusion_dir", "data_dir")


def machine() -> dict:
  """CPU model, visible cores and the 1-minute load average at the time of the call."""
  model = next(
      (
          line.split(":", 1)[1].strip()
          for line in open("/proc/cpuinfo")
          if line.startswith("model name")
      ),
      "unknown",
  )
  return {
      "cpu": model,
      "cores": os.cpu_count(),
      "load_1min": os.getloadavg()[0],
      "backend": jax.default_backend(),
      "jax": jax.__version__,
  }


def frame(data_dir, vehicles: int):
  test = dataset.load_split(data_dir, "test")
  if len(test) < vehicles:
    raise ValueError(f"--vehicles={vehicles}: the test split of {data_dir} has {len(test)}")
  return test.take(np.arange(vehicles))


def call_times(fn, calls: int) -> dict:
  """ms of the first call and median / p90 of `calls` calls after it."""
  times = []
  for _ in range(calls + 1):
    start = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(1e3 * (time.perf_counter() - start))
  warm = np.array(times[1:])
  return {
      "first_ms": times[0],
      "median_ms": float(np.median(warm)),
      "p90_ms": float(np.percentile(warm, 90)),
  }


def with_samples(predictor: Predictor, n: int, chunk: int) -> Predictor:
  return dataclasses.replace(
      predictor, chunk_size=chunk, sampling=dataclasses.replace(predictor.sampling, num_samples=n)
  )


def parts(predictor: Predictor, scenarios, calls: int) -> dict:
  """Median ms of each stage of the prediction, each jitted alone (module docstring, 2)."""
  xi, mask = jax.numpy.asarray(scenarios.xi), jax.numpy.asarray(scenarios.mask)
  tok = jax.jit(lambda x, m: (predictor.tokenizer.tokenize(x, m), ego_motion.ego_features(x, m)))
  out = predictor(scenarios, seed=0).prediction
  v0, psi0 = (jax.numpy.asarray(a, jax.numpy.float32) for a in (scenarios.v0, scenarios.psi0))
  rollout = jax.jit(lambda c: vmm.rollout(c, v0[:, None], psi0[:, None]))
  hyp = jax.jit(lambda t: fit_hypotheses(t, config=predictor.sampling.hypotheses))
  whole = lambda: predictor(scenarios, seed=0).prediction.mean
  timed = {
      "tokeniser": lambda: tok(xi, mask),
      "vmm": lambda: rollout(out.controls),
      "hypotheses": lambda: hyp(out.trajectories),
      "whole": whole,
  }
  ms = {name: call_times(fn, calls)["median_ms"] for name, fn in timed.items()}
  ms["sampler (whole - others)"] = ms["whole"] - ms["tokeniser"] - ms["vmm"] - ms["hypotheses"]
  return ms


def frame_times(samples) -> dict:
  """{n: `call_times` of the frame with n samples a vehicle} (module docstring, 1)."""
  base = Predictor.load(_TOKENIZER.value, _DIFFUSION.value)
  scenarios = frame(_DATA.value, _VEHICLES.value)
  return {
      n: call_times(
          lambda p=with_samples(base, n, _VEHICLES.value): p(scenarios, seed=0).prediction.mean,
          _CALLS.value,
      )
      for n in samples
  }


def run_child(*args: str, env=None) -> dict:
  """This script in a fresh process with `args` (after the run and data flags): the JSON
  of its last stdout line; its one-line error (without "<script>: error: ") raised."""
  cmd = [
      sys.executable,
      __file__,
      *(
          f"--{f}={getattr(flags.FLAGS, f)}"
          for f in ("tokenizer_dir", "diffusion_dir", "data_dir", "vehicles", "calls")
      ),
      *args,
  ]
  done = subprocess.run(cmd, capture_output=True, text=True, env=env)
  if done.returncode:
    last = (done.stderr.strip() or "?").splitlines()[-1]
    raise UserError(f"{' '.join(args)}: {last.split(': error: ', 1)[-1]}")
  return json.loads(done.stdout.strip().splitlines()[-1])


def frames_by_devices(samples) -> list:
  """[{"host_devices": count, "samples": `frame_times`}] per --host_devices, each in a
  fresh process (a count may repeat: runs alternated) whose XLA_FLAGS lose any count."""
  xla_flags = sharding.HOST_DEVICES_PATTERN.sub("", os.environ.get("XLA_FLAGS", ""))
  env = dict(os.environ, XLA_FLAGS=xla_flags.strip())
  results = []
  for count in (int(c) for c in _HOST.value):
    rows = run_child(
        "--child=frame",
        f"--host_devices={count}",
        f"--samples={','.join(str(n) for n in samples)}",
        env=env,
    )
    results.append({"host_devices": count, "samples": {int(n): r for n, r in rows.items()}})
  return results


def child(kind: str) -> dict:
  """One first call in this fresh process (module docstring, 3), seconds."""
  scenarios = frame(_DATA.value, _VEHICLES.value)
  n = int(_SAMPLES.value[0])
  start = time.perf_counter()
  if kind == "package":
    predictor = with_samples(Predictor.load(_TOKENIZER.value, _DIFFUSION.value), n, _VEHICLES.value)
    loaded = time.perf_counter()
    jax.block_until_ready(predictor(scenarios, seed=0).prediction.mean)
  else:
    exported = jax.export.deserialize((Path(_EXPORT_DIR.value) / export.PREDICT_FILE).read_bytes())
    loaded = time.perf_counter()
    jax.block_until_ready(exported.call(*export.call_inputs(scenarios, 0))["mean"])
  done = time.perf_counter()
  return {"load_s": loaded - start, "first_call_s": done - loaded}


def first_calls(predictor: Predictor, runs: int) -> dict:
  """{package, exported: median {load_s, first_call_s} over `runs` fresh processes}."""
  results = {}
  with tempfile.TemporaryDirectory() as tmp:
    export.export(with_samples(predictor, int(_SAMPLES.value[0]), _VEHICLES.value), tmp)
    for kind in ("package", "exported"):
      rows = [
          run_child(f"--child={kind}", f"--export_dir={tmp}", f"--samples={_SAMPLES.value[0]}")
          for _ in range(runs)
      ]
      results[kind] = {k: statistics.median(r[k] for r in rows) for k in rows[0]}
  return results


def main(argv):
  del argv
  if _CHILD.value == "frame":
    sharding.use_host_devices(int(_HOST.value[0]))
    print(json.dumps(frame_times([int(s) for s in _SAMPLES.value])))
    return
  if _CHILD.value:
    print(json.dumps(child(_CHILD.value)))
    return
  samples = [int(s) for s in _SAMPLES.value]
  info = machine()
  print(f"machine: {info}")
  base = Predictor.load(_TOKENIZER.value, _DIFFUSION.value)
  scenarios = frame(_DATA.value, _VEHICLES.value)
  result = {
      "machine": info,
      "vehicles": _VEHICLES.value,
      "calls": _CALLS.value,
      "sampler": f"{base.sampling.sampler}({base.sampling.steps})",
      "frame": frames_by_devices(samples),
  }
  first = result["frame"][0]["samples"]
  for run in result["frame"]:
    for n, row in run["samples"].items():
      print(
          f"{_VEHICLES.value} vehicles, {n} samples, {run['host_devices']} host devices: first "
          f"{row['first_ms']:.0f} ms, median {row['median_ms']:.1f} ms, p90 "
          f"{row['p90_ms']:.1f} ms ({first[n]['median_ms'] / row['median_ms']:.2f}x the first)"
      )
  result["parts_ms"] = parts(
      with_samples(base, samples[0], _VEHICLES.value), scenarios, _CALLS.value
  )
  print(
      f"parts ({samples[0]} samples, median ms): "
      + ", ".join(f"{k} {v:.1f}" for k, v in result["parts_ms"].items())
  )
  if _RUNS.value:
    result["first_call"] = first_calls(base, _RUNS.value)
    for kind, row in result["first_call"].items():
      print(
          f"fresh process, {kind}: load {row['load_s']:.2f} s, first call "
          f"{row['first_call_s']:.2f} s"
      )
  result["machine"]["load_1min_end"] = os.getloadavg()[0]
  if _OUT.value:
    atomic.write_json(_OUT.value, result)


if __name__ == "__main__":
  cli.run(main)
