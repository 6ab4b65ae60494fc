"""Data parallelism over all visible devices with `jax.sharding`.

One 1-D mesh with axis "data": model state is replicated on every device, batches are
split along their leading (example) dimension. Training and batched inference both use
it; on CPU, `XLA_FLAGS=--xla_force_host_platform_device_count=N` (set before jax starts)
gives N devices: `use_host_devices` sets it. One device per core predicts faster than one
device on all of them (a frame of 30 vehicles on 2 cores: docs/benchmarks.md); the outputs
equal one device's to float rounding (a device's batch is another size).

Several processes (hosts): `initialize_distributed` (`distributed.launch`, re-exported here)
joins a `jax.distributed` run described by the environment (JAX_* variables, or the
cluster's launcher: mpirun, srun, a Kubernetes indexed Job, detected through JAX's own
cluster classes); the mesh then spans the devices of every process, each process puts only
its own rows of a global batch on its own devices (`shard_batch`), and `local_copy` gives a
process its copy of a replicated state for single-process code. `check_same_run` makes every
process compare its run's identity with process 0's before any work.
"""

import json
import os
import re
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from cvmdx_jax.distributed.launch import (  # re-exported: the entry points call sharding.*
    ENV_COORDINATOR,
    ENV_NUM_PROCESSES,
    ENV_PROCESS_ID,
    HEARTBEAT_S,
    SHUTDOWN_S,
    cluster_launcher,
    detect_cluster,
    initialize_distributed,
)
from cvmdx_jax.errors import UserError
from cvmdx_jax.storage import identity

DATA_AXIS = "data"
HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"
HOST_DEVICES_PATTERN = re.compile(rf"{HOST_DEVICES_FLAG}=(\d+)")  # the flag in XLA_FLAGS

__all__ = [
    "DATA_AXIS",
    "ENV_COORDINATOR",
    "ENV_NUM_PROCESSES",
    "ENV_PROCESS_ID",
    "HEARTBEAT_S",
    "SHUTDOWN_S",
    "ProcessMismatchError",
    "batch_sharding",
    "check_divisible",
    "check_same_run",
    "cluster_launcher",
    "data_mesh",
    "detect_cluster",
    "initialize_distributed",
    "is_primary",
    "local_copy",
    "pad_batch",
    "replicate",
    "replicated",
    "shard_batch",
    "use_host_devices",
]


class ProcessMismatchError(UserError):
  """The processes of one `jax.distributed` run were started with different runs."""


def check_same_run(fingerprint: Any, what: str = "run") -> None:
  """Raises `ProcessMismatchError` in every process when any process's `fingerprint`
  (JSON-able: config, dataset id, ...) differs from process 0's; all processes must call
  it together. The message names the first differing process and every differing key.
  One process: returns at once."""
  if jax.process_count() == 1:
    return
  from jax.experimental import multihost_utils

  mine = json.dumps(identity.to_json(fingerprint), sort_keys=True).encode()
  sizes = multihost_utils.process_allgather(np.int32(len(mine)))
  padded = np.zeros(int(np.max(sizes)), np.uint8)
  padded[: len(mine)] = np.frombuffer(mine, np.uint8)
  texts = multihost_utils.process_allgather(padded)
  runs = [json.loads(bytes(t[:n])) for t, n in zip(texts, sizes)]
  for index, run in enumerate(runs[1:], start=1):
    diffs = identity.differing_keys(run, runs[0], names=(f"process {index}", "process 0"))
    if diffs:
      raise ProcessMismatchError(
          f"process {index} of {len(runs)} was started with another "
          f"{what} than process 0; differing keys: " + "; ".join(diffs) + "; nothing was written"
      )


def is_primary() -> bool:
  """True in process 0, the one process that writes logs and JSON files of a run."""
  return jax.process_index() == 0


def data_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
  """A 1-D mesh with axis "data" over `devices` (default: all visible devices)."""
  devices = jax.devices() if devices is None else list(devices)
  if not devices:
    raise ValueError("data_mesh: no devices given")
  return Mesh(np.asarray(devices), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
  """The sharding that keeps a full copy of an array on every device of `mesh`."""
  return NamedSharding(mesh, P())


def batch_sharding(mesh: Mesh) -> NamedSharding:
  """The sharding that splits an array's leading dimension over the "data" axis."""
  return NamedSharding(mesh, P(DATA_AXIS))


def check_divisible(batch_size: int, mesh: Mesh, name: str = "batch_size") -> None:
  """Raises ValueError unless `batch_size` splits evenly over the devices of `mesh`."""
  n = mesh.shape[DATA_AXIS]
  if batch_size <= 0 or batch_size % n:
    raise UserError(
        f"{name}={batch_size} must be a positive multiple of the number of devices ({n}); "
        f"choose {name} divisible by {n} or run on fewer devices"
    )


def replicate(tree: Any, mesh: Mesh) -> Any:
  """Places every array of `tree` fully on every device of `mesh`."""
  return jax.device_put(tree, replicated(mesh))


def shard_batch(batch: Any, mesh: Mesh) -> Any:
  """Splits every array of `batch` along its leading dimension over the "data" axis.

  Args:
    batch: a pytree of arrays, all with the same leading dimension B.
    mesh: the mesh from `data_mesh`.

  With several processes every process passes the same global `batch` (host arrays) and
  transfers only the rows of its own devices.

  Returns:
    The same pytree as global `jax.Array`s sharded `P("data")`.

  Raises:
    ValueError: B is not a multiple of the device count (pad first with `pad_batch`).
  """
  sizes = {np.shape(x)[0] if np.ndim(x) else None for x in jax.tree.leaves(batch)}
  if len(sizes) != 1 or None in sizes:
    raise ValueError(f"shard_batch: leaves need one common leading dimension, got {sizes}")
  check_divisible(sizes.pop(), mesh, "batch leading dimension")
  split = batch_sharding(mesh)
  if split.is_fully_addressable:
    return jax.device_put(batch, split)
  return jax.tree.map(
      lambda x: jax.make_array_from_callback(
          np.shape(x), split, lambda index: np.asarray(x[index])
      ),
      batch,
  )


def local_copy(tree: Any) -> Any:
  """This process's copy (on its first local device) of a replicated pytree; as is when
  one process addresses every device."""
  return jax.tree.map(lambda x: x if x.is_fully_addressable else x.addressable_data(0), tree)


def pad_batch(batch: Any, multiple: int) -> tuple[Any, np.ndarray]:
  """Pads the leading dimension of every array up to a multiple of `multiple` (host side).

  Padding rows are copies of the first rows (cyclically), so they hold realistic, finite
  values; the returned weight marks them 0 so that losses and statistics ignore them.

  Args:
    batch: a pytree of arrays, all with the same leading dimension B >= 1.
    multiple: the padded size is the smallest multiple of it that is >= B.

  Returns:
    (padded, weight): `padded` has leading dimension B' = ceil(B / multiple) * multiple;
    `weight` (B',) float32 is 1 for the B real rows and 0 for padding rows.
  """
  if multiple <= 0:
    raise ValueError(f"pad_batch: multiple={multiple} must be positive")
  sizes = {np.shape(x)[0] if np.ndim(x) else None for x in jax.tree.leaves(batch)}
  if len(sizes) != 1 or None in sizes or 0 in sizes:
    raise ValueError(
        f"pad_batch: leaves need one common, non-zero leading dimension, " f"got {sizes}"
    )
  n = sizes.pop()
  pad = -n % multiple
  weight = np.concatenate([np.ones(n, np.float32), np.zeros(pad, np.float32)])
  if not pad:
    return batch, weight
  extra = np.arange(pad) % n
  padded = jax.tree.map(lambda x: np.concatenate([np.asarray(x), np.asarray(x)[extra]]), batch)
  return padded, weight


def use_host_devices(count: int) -> None:
  """Makes this process's CPU `count` JAX devices (through XLA_FLAGS); the data mesh then
  splits a batch over them. Call before JAX's first computation.

  Raises:
    UserError: count < 1, XLA_FLAGS already sets another count, or JAX started before the
      call (count > 1).
  """
  if count < 1:
    raise UserError(f"host devices: {count}, expected at least 1")
  xla_flags = os.environ.get("XLA_FLAGS", "")
  found = HOST_DEVICES_PATTERN.search(xla_flags)
  if found and int(found.group(1)) != count:
    raise UserError(
        f"XLA_FLAGS sets {HOST_DEVICES_FLAG}={found.group(1)}, which contradicts {count} "
        "host devices: set one of them"
    )
  if found or count == 1:  # XLA's own count (1) or the one XLA_FLAGS sets: JAX not started
    return
  os.environ["XLA_FLAGS"] = f"{xla_flags} {HOST_DEVICES_FLAG}={count}".strip()
  have = len(jax.devices("cpu"))
  if have != count:
    raise UserError(
        f"JAX started with {have} CPU devices before {count} host devices were asked for: "
        "ask before the first computation"
    )
