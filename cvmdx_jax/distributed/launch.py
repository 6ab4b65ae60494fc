"""Joining a multi-process `jax.distributed` run: the launcher that started this process
(mpirun, srun, a Kubernetes indexed Job, or the JAX_* variables), its coordinator, process
count and id, and `initialize_distributed`, which process 0 runs with the coordination service
in a child process (`distributed.coordination`). `cvmdx_jax.sharding` re-exports the public
names (the entry points call `sharding.initialize_distributed`)."""

import contextlib
import os
from collections.abc import Mapping

import jax

from cvmdx_jax.distributed import coordination
from cvmdx_jax.errors import UserError

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
