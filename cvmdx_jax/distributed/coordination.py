"""The coordination service of a `jax.distributed` run, hosted in a small child of process 0.

JAX runs the service (key-value store, barriers, heartbeats) inside process 0. When process 0
dies, every other process's client loses it and JAX aborts that process within a second,
with a multi-line log. `distributed.launch.initialize_distributed` makes process 0 start the service
through `start` instead: a child process (`python -m cvmdx_jax.distributed.coordination`,
jaxlib only) that serves until process 0 shuts it down, or outlives a dead process 0 by `GRACE_S`
seconds: long enough for the other processes to find process 0 silent
(`train.preemption.PeerWatch`: one line, status 75) or for JAX's own heartbeat timeout to
stop them. The child ignores SIGINT and SIGTERM (a Ctrl-C or a preemption reaches every
process of the run, which must still agree on where to stop and save through the service).

Protocol: the child prints one line on stdout ("ready", or "error: <why>") once the service
listens; then it reads stdin to its end. "done" (process 0's clean shutdown, after every
process passed JAX's shutdown barrier) ends it at once; an end of file without it (process
0 died or left with `os._exit`) ends it after `GRACE_S`.
"""

import errno
import json
import os
import signal
import socket
import subprocess
import sys
import time

from cvmdx_jax.errors import UserError

GRACE_S = 30.0  # > PeerWatch's 10 s silence and the coordinator's 20 s heartbeat timeout
_SHUTDOWN_S = 60.0  # the wait for the service's own shutdown, then it is killed
_DONE = b"done"


def _port(bind_address: str) -> int:
  return int(bind_address.rsplit(":", 1)[1])


def port_in_use(port: int) -> bool:
  """Whether a socket listens on TCP `port` of this host (any address): a plain bind of it
  fails. gRPC binds with SO_REUSEPORT, so a second service would share the port silently."""
  with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # past TIME_WAIT: free
    try:
      probe.bind(("0.0.0.0", port))
    except OSError as e:
      if e.errno == errno.EADDRINUSE:
        return True
      raise
  return False


class ServiceHost:
  """Process 0's handle of the service child, in the place of JAX's in-process service
  (`jax._src.distributed.global_state.service`): JAX calls `shutdown` after the clients'."""

  def __init__(self, child: subprocess.Popen):
    self._child = child

  def shutdown(self) -> None:
    """Ends the service now (every process is past JAX's shutdown barrier)."""
    child = self._child
    try:
      if child.poll() is None:
        child.stdin.write(_DONE)
      child.stdin.close()
    except BrokenPipeError:
      pass  # it had ended
    try:
      child.wait(timeout=_SHUTDOWN_S)
    except subprocess.TimeoutExpired:
      child.kill()
      child.wait()
    child.stdout.close()


def start(address: str, num_nodes: int, **options) -> ServiceHost:
  """Starts the coordination service on `address` ("[::]:port") for `num_nodes` processes
  in a child process; `options` are those of jaxlib's `get_distributed_runtime_service`
  (JSON values). Waits up to `GRACE_S` for the port of a dead run's service to free.

  Raises:
    UserError: the port is taken, or the service does not start (the reason named).
  """
  port = _port(address)
  deadline = time.monotonic() + GRACE_S + 5
  while port_in_use(port):
    if time.monotonic() > deadline:
      raise UserError(
          f"the coordinator port {port} (JAX_COORDINATOR_ADDRESS) is in use by another "
          "program; choose a free port"
      )
    time.sleep(1.0)
  service = {"address": address, "num_nodes": num_nodes, **options}
  args = json.dumps({"service_args": service, "grace_s": GRACE_S})
  child = subprocess.Popen(
      [sys.executable, "-m", "cvmdx_jax.distributed.coordination", args],
      stdin=subprocess.PIPE,
      stdout=subprocess.PIPE,
      stderr=subprocess.DEVNULL,
  )
  line = child.stdout.readline().decode().strip()
  if line != "ready":
    child.kill()
    child.wait()
    child.stdin.close()
    child.stdout.close()
    reason = line.removeprefix("error: ") or f"it exited with status {child.returncode}"
    raise UserError(f"the coordination service on {address} did not start: {reason}")
  return ServiceHost(child)


def serve(service_args: dict, grace_s: float) -> None:
  """The child: runs jaxlib's service with `service_args` until stdin says so, or until
  `grace_s` after its end (module docstring)."""
  for number in (signal.SIGINT, signal.SIGTERM):
    signal.signal(number, signal.SIG_IGN)
  from jaxlib import _jax  # pylint: disable=import-outside-toplevel

  try:
    service = _jax.get_distributed_runtime_service(**service_args)
  except Exception as e:  # pylint: disable=broad-except
    print(f"error: {' '.join(str(e).split())}", flush=True)
    return
  print("ready", flush=True)
  said = sys.stdin.buffer.read()
  if said != _DONE:  # process 0 died: let the others find out through the service
    time.sleep(grace_s)
  else:
    service.shutdown()
  os._exit(0)  # pylint: disable=protected-access


if __name__ == "__main__":
  serve(**json.loads(sys.argv[1]))
