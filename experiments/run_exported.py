"""Runs an exported cVMDx (experiments/export.py) with JAX and numpy alone: it imports
nothing of cvmdx_jax, so it works in any environment with `jax` (the version in the
manifest or newer) installed, and is the example to copy into another code base.

  python experiments/run_exported.py --export_dir=runs/demo/export \\
      --inputs=scenarios.npz --out=predictions.npz --seed=0

scenarios.npz holds the inputs of the manifest's "predict" entry: xi (M, 9, 75, 4) float32,
mask (M, 9, 75) bool, v0 (M,), psi0 (M,) float32 (road frame of the ego at t0, as in
docs/design.md), and noise_ids (M, K) uint32 where the export's K is not 1 (for K = 1 the
default is 0..M-1: scenario i draws its noise from fold_in(key(seed), noise_ids[i, 0]); the
manifest's "keys" entry). predictions.npz gets every output named in the
manifest. Each artefact's sha256 is checked against checksums.json before it is loaded.
Not an absl script (it must not need this package): a bad input is one line on stderr and
exit status 2; Ctrl-C (SIGTERM) one line and status 130 (143), from the imports on.
"""

import argparse
import hashlib
import json
import os
import signal
import sys
from pathlib import Path


def _stop(signum, frame) -> None:
  """SIGINT / SIGTERM: one line, exit 130 / 143 (--out is written only whole)."""
  del frame
  what = "interrupted" if signum == signal.SIGINT else "terminated"
  print(f"run_exported: error: {what}", file=sys.stderr, flush=True)
  os._exit(128 + signum)  # JAX's exit handlers can crash an interrupted interpreter


if __name__ == "__main__":  # before the seconds of JAX's import; an ignored signal stays so
  if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    signal.signal(signal.SIGINT, _stop)
  if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
    signal.signal(signal.SIGTERM, _stop)

import jax  # noqa: E402
import numpy as np  # noqa: E402


def fail(message: str):
  print(f"run_exported: error: {message}", file=sys.stderr)
  sys.exit(2)


def read_verified(directory: Path, name: str) -> bytes:
  """The bytes of directory/name, checked against its sha256 in checksums.json."""
  try:
    data = (directory / name).read_bytes()
    listed = json.loads((directory / "checksums.json").read_text())[name]
  except (OSError, ValueError, KeyError) as e:
    fail(f"{directory / name}: cannot read it or its checksum ({e!r})")
  listed = [listed] if isinstance(listed, str) else listed
  if hashlib.sha256(data).hexdigest() not in listed:
    fail(f"{directory / name}: content does not match checksums.json (corrupt copy?)")
  return data


def load_inputs(path: Path, specs: list[dict]) -> dict:
  """{name: array} for every "b"-batched input of `specs` from the npz at `path`."""
  try:
    arrays = dict(np.load(path))
  except (OSError, ValueError) as e:
    fail(f"--inputs={path}: not a readable .npz ({e})")
  batched = [s for s in specs if s["shape"][:1] == ["b"]]
  m = len(arrays["xi"]) if "xi" in arrays else 0
  if [s["shape"] for s in specs if s["name"] == "noise_ids"] == [["b", 1]]:
    arrays.setdefault("noise_ids", np.arange(m)[:, None])
  out = {}
  for spec in batched:
    name = spec["name"]
    if name not in arrays:
      fail(f"--inputs={path}: field '{name}' missing (needs {[s['name'] for s in batched]})")
    value = np.asarray(arrays[name]).astype(spec["dtype"])
    expected = [m] + spec["shape"][1:]
    if list(value.shape) != expected or not m:
      fail(f"--inputs={path}: field '{name}' has shape {value.shape}, expected {expected}")
    out[name] = value
  return out


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
  parser.add_argument("--export_dir", required=True, type=Path)
  parser.add_argument("--inputs", required=True, type=Path)
  parser.add_argument("--out", required=True, type=Path)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args(argv)
  if not 0 <= args.seed < 2**32:
    fail(f"--seed={args.seed}: must be in [0, 2**32)")
  manifest = json.loads(read_verified(args.export_dir, "manifest.json"))
  entry = manifest["predict"]
  exported = jax.export.deserialize(read_verified(args.export_dir, entry["file"]))
  inputs = load_inputs(args.inputs, entry["inputs"])
  call_args = [
      np.uint32(args.seed) if s["name"] == "seed" else inputs[s["name"]] for s in entry["inputs"]
  ]
  outputs = jax.device_get(exported.call(*call_args))
  tmp = args.out.with_name(f".{args.out.name}.tmp")  # renamed when whole: never half-written
  with open(tmp, "wb") as f:
    np.savez(f, **{k: np.asarray(v) for k, v in outputs.items()})
  os.replace(tmp, args.out)
  print(f"wrote {args.out}: {', '.join(sorted(outputs))} for {len(inputs['xi'])} scenarios")


if __name__ == "__main__":
  main()
