"""Data parallelism over all visible devices with `jax.sharding`.

One 1-D mesh with axis "data": model state is replicated on every device, batches are
split along their leading (example) dimension. Training and batched inference both use
it; on CPU, `XLA_FLAGS=--xla_force_host_platform_device_count=N` (set before jax is
imported) gives N devices to test with.

Several processes (hosts): `initialize_distributed` joins a `jax.distributed` run described
by the environment (JAX_* variables, or the cluster's launcher: mpirun, srun, a Kubernetes
indexed Job, detected through JAX's own cluster classes); the mesh then spans the devices
of every process, each process puts only its own rows of a global batch on its own devices
(`shard_batch`), and `local_copy` gives a process its copy of a replicated state for
single-process code. `check_same_run` makes
every process compare its run's identity with process 0's before any work.
"""

import contextlib
import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from cvmdx_jax.distributed import coordination
from cvmdx_jax.errors import UserError
from cvmdx_jax.storage import identity

DATA_AXIS = "data"
ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"
ENV_NUM_PROCESSES = "JAX_NUM_PROCESSES"
ENV_PROCESS_ID = "JAX_PROCESS_ID"
# A process that sent no heartbeat for HEARTBEAT_S seconds is dead to the coordinator, which
# then stops every other process; SHUTDOWN_S bounds the wait for peers at exit.
HEARTBEAT_S = 20
SHUTDOWN_S = 30


def _env_int(env: Mapping[str, str], name: str) -> int | None:
  if not env.get(name):
    return None
  try:
    return int(env[name])
  except ValueError:
    raise UserError(f"environment variable {name}={env[name]!r} must be an integer") from None


def cluster_launcher(env: Mapping[str, str] | None = None) -> str | None:
  """The launcher of several processes that started this one, by JAX's cluster names.

  "ompi" (`mpirun -np N`, Open MPI 4: OMPI_MCA_orte_hnp_uri, OMPI_COMM_WORLD_SIZE > 1),
  "slurm" (`srun -n N`: SLURM_JOB_ID, SLURM_STEP_NODELIST, SLURM_NTASKS > 1, SLURM_PROCID,
  SLURM_LOCALID) or "k8s" (a pod of an indexed Kubernetes Job: KUBERNETES_SERVICE_HOST and
  JOB_COMPLETION_INDEX); None for a process started alone (one task of a launcher too).
  """
  env = os.environ if env is None else env
  if "OMPI_MCA_orte_hnp_uri" in env and (_env_int(env, "OMPI_COMM_WORLD_SIZE") or 1) > 1:
    return "ompi"
  slurm = ("SLURM_JOB_ID", "SLURM_STEP_NODELIST", "SLURM_PROCID", "SLURM_LOCALID")
  if all(k in env for k in slurm) and (_env_int(env, "SLURM_NTASKS") or 1) > 1:
    return "slurm"
  if "KUBERNETES_SERVICE_HOST" in env and "JOB_COMPLETION_INDEX" in env:
    return "k8s"
  return None


_JAX_CLUSTERS = {"ompi": "OmpiCluster", "slurm": "SlurmCluster", "k8s": "K8sCluster"}


def detect_cluster(launcher: str, timeout_s: int = 300) -> tuple[str, int, int, list[int] | None]:
  """(coordinator host:port, process count, process id, local device ids) of `launcher`
  (`cluster_launcher`), from JAX's own cluster classes (`jax._src.clusters`) reading
  `os.environ`; JAX_COORDINATOR_ADDRESS (or JAX_COORDINATOR_PORT) and JAX_PROCESS_ID set
  in the environment win. `timeout_s` bounds the wait for a Kubernetes coordinator pod.

  Raises:
    UserError: the launcher's environment is incomplete (e.g. no `kubernetes` package).
  """
  from jax._src import clusters  # pylint: disable=import-outside-toplevel

  known = clusters.ClusterEnv._cluster_types  # pylint: disable=protected-access
  kinds = {kind.__name__: kind for kind in known}
  kind, env = kinds[_JAX_CLUSTERS[launcher]], os.environ
  if not kind.is_env_present():
    hint = " (pip install kubernetes)" if launcher == "k8s" else ""
    raise UserError(
        f"the {launcher} launcher's environment is incomplete{hint}; or set "
        f"{ENV_COORDINATOR}, {ENV_NUM_PROCESSES} and {ENV_PROCESS_ID}"
    )
  coordinator = env.get(ENV_COORDINATOR) or kind.get_coordinator_address(
      timeout_s, env.get("JAX_COORDINATOR_PORT")
  )
  index = _env_int(env, ENV_PROCESS_ID)
  local = kind.get_local_process_id()
  return (
      coordinator,
      kind.get_process_count(),
      kind.get_process_id() if index is None else index,
      None if local is None else [local],
  )


def initialize_distributed(env: Mapping[str, str] | None = None) -> tuple[int, int]:
  """Joins a multi-process `jax.distributed` run when the environment describes one.

  Must run before anything touches a JAX backend. A run is described either by
  JAX_COORDINATOR_ADDRESS (host:port of process 0, reachable from every process),
  JAX_NUM_PROCESSES and JAX_PROCESS_ID (0 .. JAX_NUM_PROCESSES - 1), or by the cluster's
  launcher (`cluster_launcher`: mpirun, srun, a Kubernetes indexed Job), whose values
  the JAX_* variables override. Without either (or with one process) nothing happens.
  On CPU the processes talk through gloo. Process 0 hosts the coordination service in a
  child process (`distributed.coordination`) that outlives it by `coordination.GRACE_S`.
  The coordinator takes a process that sent no heartbeat for HEARTBEAT_S seconds for dead
  and stops the others (JAX aborts them); during training a collective that fails on a dead
  peer, or a peer silent for 10 s, stops them first with one line
  (`train.preemption.lost_peer`).

  Args:
    env: the environment (default `os.environ`).

  Returns:
    (process index, process count).

  Raises:
    ValueError: a variable is not an integer, the coordinator address is missing, or the
      process id is out of range (named in the message).
  """
  env = os.environ if env is None else env
  count, index = _env_int(env, ENV_NUM_PROCESSES), _env_int(env, ENV_PROCESS_ID)
  launcher = None if count is not None else cluster_launcher(env)
  if jax.distributed.is_initialized() or (launcher is None and (count or 1) == 1):
    return jax.process_index(), jax.process_count()
  local_ids = None
  if launcher is not None:
    coordinator, count, index, local_ids = detect_cluster(launcher)
  elif not env.get(ENV_COORDINATOR):
    raise UserError(
        f"{ENV_NUM_PROCESSES}={count} needs {ENV_COORDINATOR}=host:port of " "process 0"
    )
  else:
    coordinator = env[ENV_COORDINATOR]
  if index is None or not 0 <= index < count:
    raise UserError(
        f"{ENV_PROCESS_ID}={index} must be in 0..{count - 1} " f"({ENV_NUM_PROCESSES}={count})"
    )
  jax.config.update("jax_cpu_collectives_implementation", "gloo")
  with _service_in_a_child():
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=count,
        process_id=index,
        local_device_ids=local_ids,
        cluster_detection_method="deactivate",
        heartbeat_timeout_seconds=HEARTBEAT_S,
        shutdown_timeout_seconds=SHUTDOWN_S,
    )
  return jax.process_index(), jax.process_count()


class _ServiceInAChild:
  """jaxlib's module as `jax._src.distributed` sees it, but its coordination service is
  `coordination.start`'s child process."""

  def __init__(self, jaxlib_module):
    self._jaxlib = jaxlib_module

  def __getattr__(self, name: str):
    return getattr(self._jaxlib, name)

  @staticmethod
  def get_distributed_runtime_service(address, num_nodes, **options):
    return coordination.start(address, num_nodes, **options)


@contextlib.contextmanager
def _service_in_a_child():
  """While entered, `jax.distributed.initialize` in process 0 starts the coordination
  service in a child process (`distributed.coordination`: the others then outlive process 0
  long enough to stop with one line) instead of in this process."""
  from jax._src import distributed  # pylint: disable=import-outside-toplevel

  jaxlib_module = distributed._jax  # pylint: disable=protected-access
  distributed._jax = _ServiceInAChild(jaxlib_module)  # pylint: disable=protected-access
  try:
    yield
  finally:
    distributed._jax = jaxlib_module  # pylint: disable=protected-access


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
