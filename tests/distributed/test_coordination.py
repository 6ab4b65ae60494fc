"""The coordination service's child process (cvmdx_jax.distributed.coordination); the 2-process runs
that rely on it are in tests/train/test_distributed.py."""

import signal
import socket
import time

import pytest

from cvmdx_jax.distributed import coordination
from cvmdx_jax.errors import UserError


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _exit_time(child, limit_s: float) -> float:
  """Seconds until `child` exits (at most `limit_s`, then it is killed and the test fails)."""
  start = time.monotonic()
  while child.poll() is None:
    if time.monotonic() - start > limit_s:
      child.kill()
      child.wait()
      pytest.fail(f"the service child still runs after {limit_s} s")
    time.sleep(0.05)
  return time.monotonic() - start


def test_port_in_use_sees_a_listener_and_not_a_closed_socket():
  with socket.socket() as listener:
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    assert coordination.port_in_use(port)
  assert not coordination.port_in_use(port)


def test_the_service_ignores_signals_and_ends_at_once_on_a_clean_shutdown():
  port = _free_port()
  host = coordination.start(f"[::]:{port}", 2, heartbeat_timeout=20)
  child = host._child
  try:
    assert coordination.port_in_use(port)  # it listens
    child.send_signal(signal.SIGINT)  # a Ctrl-C reaches every process of a run
    child.send_signal(signal.SIGTERM)  # so does a preemption: the run still saves through it
    time.sleep(0.5)
    assert child.poll() is None
  finally:
    host.shutdown()
  assert child.returncode == 0 and not coordination.port_in_use(port)


def test_the_service_outlives_a_dead_parent_by_the_grace_period(monkeypatch):
  monkeypatch.setattr(coordination, "GRACE_S", 3.0)
  port = _free_port()
  host = coordination.start(f"[::]:{port}", 2)
  child = host._child
  child.stdin.close()  # what process 0's death (or its os._exit) looks like to the child
  took = _exit_time(child, 60)
  child.stdout.close()
  assert 3.0 <= took < 30, took
  assert not coordination.port_in_use(port)


def test_a_taken_port_is_refused_naming_it(monkeypatch):
  monkeypatch.setattr(coordination, "GRACE_S", 0.0)  # waits 5 s for the port, no longer
  with socket.socket() as listener:
    listener.bind(("0.0.0.0", 0))
    listener.listen()
    port = listener.getsockname()[1]
    with pytest.raises(UserError, match=f"coordinator port {port} .* is in use"):
      coordination.start(f"[::]:{port}", 2)
