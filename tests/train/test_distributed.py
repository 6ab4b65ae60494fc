"""Training under `jax.distributed`: several local CPU processes on 127.0.0.1 (toy_job.py)."""

import json
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cvmdx_jax import sharding
from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[2]
JOB = REPO / "tests" / "train" / "toy_job.py"


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _launch(workdir, processes: int, devices: int = 1, own=(), **args) -> list[subprocess.Popen]:
  """Starts one run of toy_job.py as `processes` processes with `devices` CPU devices each;
  `own[i]` (a dict) adds arguments of process i."""
  env = environ(XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
                JAX_PLATFORMS="cpu")
  if processes > 1:
    env.update(JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{_free_port()}",
               JAX_NUM_PROCESSES=str(processes))
  cmd = [sys.executable, str(JOB), f"--workdir={workdir}"] + [f"--{k}={v}" for k, v in args.items()]
  own = list(own) + [{}] * (processes - len(own))
  return [subprocess.Popen(cmd + [f"--{k}={v}" for k, v in own[i].items()],
                           env={**env, "JAX_PROCESS_ID": str(i)}, text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE)
          for i in range(processes)]


def _finish(procs) -> list[tuple[int, str, str]]:
  """(exit status, stdout, stderr) of each process; kills all on a timeout."""
  try:
    outs = [p.communicate(timeout=240) for p in procs]
  finally:
    for p in procs:
      p.kill()
  return [(p.returncode, out, err) for p, (out, err) in zip(procs, outs)]


def _results(procs) -> list[dict]:
  done = _finish(procs)
  for code, _, err in done:
    assert code == 0, err[-2000:]
  return [json.loads(out.splitlines()[-1]) for _, out, _ in done]


def _wait_for_line(proc, line: str) -> None:
  for got in proc.stdout:
    if got.strip() == line:
      return
  raise AssertionError(f"process ended before printing {line!r}: {proc.stderr.read()[-2000:]}")


def test_two_processes_match_one_process_and_write_one_run(tmp_path):
  # The 1-process reference has 2 devices too: the same split of every batch, so the
  # 2-way gradient sum is the same float32 sum and the result must be bit-identical
  # (test_loop checks 2 devices against 1).
  one = _launch(tmp_path / "one", 1, devices=2, epochs=3)
  two = _launch(tmp_path / "two", 2, devices=1, epochs=3)
  one, two = _results(one)[0], _results(two)
  assert [r["devices"] for r in two] == [2, 2] and [r["process"] for r in two] == [0, 1]
  np.testing.assert_array_equal(two[0]["params"], one["params"])
  np.testing.assert_array_equal(two[1]["params"], one["params"])
  assert two[0]["loss"] == one["loss"] and two[1]["loss"] is None  # process 0 logs
  lines = (tmp_path / "two" / "metrics.jsonl").read_text().splitlines()
  assert [json.loads(line)["epoch"] for line in lines] == [1, 2, 3]  # one writer
  assert sorted(p.name for p in (tmp_path / "two" / "checkpoints").iterdir()) == ["2", "3"]


def test_a_second_multi_process_run_is_refused_in_every_process(tmp_path):
  holder = subprocess.Popen(
      [sys.executable, "-c", "import sys, time\nfrom cvmdx_jax.storage import locking\n"
       "with locking.hold(sys.argv[1]):\n  print('held', flush=True)\n  time.sleep(600)\n",
       str(tmp_path)], stdout=subprocess.PIPE, text=True, env=environ())
  try:
    assert holder.stdout.readline().strip() == "held"
    done = _finish(_launch(tmp_path, 2, epochs=1))
  finally:
    holder.kill()
    holder.wait()
  assert [code for code, _, _ in done] == [2, 2]  # process 1 got its own lock, yet stops
  assert f"pid {holder.pid} " in done[0][2]
  assert "locked by another process" in done[1][2]
  assert sorted(p.name for p in tmp_path.iterdir()) == [".lock"]


@pytest.mark.slow  # ~56 s on the shared 2-core machine; test_sharding simulates it fast
def test_processes_started_with_other_settings_all_stop_naming_the_keys(tmp_path):
  done = _finish(_launch(tmp_path, 2, epochs=1, own=[{}, {"seed": 1, "m": 40}]))
  assert [code for code, _, _ in done] == [2, 2]
  for _, _, err in done:
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: process 1 of 2 was started with another run"), err[-2000:]
    assert "loop.seed: process 1 1, process 0 0" in line
    assert "loop.num_examples: process 1 40, process 0 36" in line and "data: process 1" in line
  assert not (tmp_path / "checkpoints").exists() and not (tmp_path / "metrics.jsonl").exists()


@pytest.mark.slow
@pytest.mark.parametrize("victim", [0, 1])
def test_sigkill_of_one_process_then_relaunch_resumes_bit_identical(tmp_path, victim):
  reference = _results(_launch(tmp_path / "ref", 2, epochs=4))[0]
  procs = _launch(tmp_path / "run", 2, epochs=4, sleep=1.0)
  _wait_for_line(procs[victim], "epoch 2")  # checkpoint 1 is complete, epoch 2's may not be
  procs[victim].send_signal(signal.SIGKILL)
  time.sleep(0.5)
  for p in procs:  # the launcher tears the job down, as a scheduler does
    p.kill()
  _finish(procs)
  assert (tmp_path / "run" / "checkpoints" / "1").is_dir()
  resumed = _results(_launch(tmp_path / "run", 2, epochs=4))
  np.testing.assert_array_equal(resumed[0]["params"], reference["params"])
  np.testing.assert_array_equal(resumed[1]["params"], reference["params"])
  lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
  assert [json.loads(line)["epoch"] for line in lines] == [1, 2, 3, 4]


@pytest.mark.parametrize("env, match", [
    ({"JAX_NUM_PROCESSES": "two"}, "JAX_NUM_PROCESSES='two' must be an integer"),
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}, "needs JAX_COORDINATOR_ADDRESS"),
    ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2", "JAX_COORDINATOR_ADDRESS": "h:1"},
     "JAX_PROCESS_ID=2 must be in 0..1"),
])
def test_bad_distributed_environment_is_named(env, match):
  with pytest.raises(ValueError, match=match):
    sharding.initialize_distributed(env)


def test_no_distributed_environment_is_one_process():
  assert sharding.initialize_distributed({}) == (0, 1)
  assert sharding.initialize_distributed({"JAX_NUM_PROCESSES": "1"}) == (0, 1)
