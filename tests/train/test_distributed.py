"""Training under `jax.distributed`: several local CPU processes on 127.0.0.1 (toy_job.py)."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from cvmdx_jax import sharding
from cvmdx_jax.storage import checkpointing
from cvmdx_jax.train import preemption
from tests.subprocess_env import environ
from tests.train import toy

REPO = Path(__file__).resolve().parents[2]
JOB = REPO / "tests" / "train" / "toy_job.py"


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _launch(workdir, processes: int, devices: int = 1, own=(), **args) -> list[subprocess.Popen]:
  """Starts one run of toy_job.py as `processes` processes with `devices` CPU devices each;
  `own[i]` (a dict) adds arguments of process i."""
  env = environ(XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}", JAX_PLATFORMS="cpu")
  if processes > 1:
    env.update(
        JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{_free_port()}", JAX_NUM_PROCESSES=str(processes)
    )
  cmd = [sys.executable, str(JOB), f"--workdir={workdir}"] + [f"--{k}={v}" for k, v in args.items()]
  own = list(own) + [{}] * (processes - len(own))
  return [
      subprocess.Popen(
          cmd + [f"--{k}={v}" for k, v in own[i].items()],
          env={**env, "JAX_PROCESS_ID": str(i)},
          text=True,
          stdout=subprocess.PIPE,
          stderr=subprocess.PIPE,
      )
      for i in range(processes)
  ]


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
      [
          sys.executable,
          "-c",
          "import sys, time\nfrom cvmdx_jax.storage import locking\n"
          "with locking.hold(sys.argv[1]):\n  print('held', flush=True)\n  time.sleep(600)\n",
          str(tmp_path),
      ],
      stdout=subprocess.PIPE,
      text=True,
      env=environ(),
  )
  try:
    assert holder.stdout.readline().strip() == "held"
    done = _finish(_launch(tmp_path, 2, epochs=1))
  finally:
    holder.kill()
    holder.wait()
    holder.stdout.close()
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


@pytest.mark.parametrize(
    "env, match",
    [
        ({"JAX_NUM_PROCESSES": "two"}, "JAX_NUM_PROCESSES='two' must be an integer"),
        ({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "0"}, "needs JAX_COORDINATOR_ADDRESS"),
        (
            {"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2", "JAX_COORDINATOR_ADDRESS": "h:1"},
            "JAX_PROCESS_ID=2 must be in 0..1",
        ),
    ],
)
def test_bad_distributed_environment_is_named(env, match):
  with pytest.raises(ValueError, match=match):
    sharding.initialize_distributed(env)


def test_no_distributed_environment_is_one_process():
  assert sharding.initialize_distributed({}) == (0, 1)
  assert sharding.initialize_distributed({"JAX_NUM_PROCESSES": "1"}) == (0, 1)


# ------------------------------------------------- the cluster's own launcher (JAX detects)

_LAUNCHER_VARS = ("OMPI_", "SLURM_", "KUBERNETES_", "JOB_COMPLETION_INDEX", "JAX_", "HOSTNAME")


def _cluster_env(monkeypatch, **variables: str) -> None:
  """os.environ without any launcher's variables, plus `variables`."""
  for name in list(os.environ):
    if name.startswith(_LAUNCHER_VARS):
      monkeypatch.delenv(name)
  for name, value in variables.items():
    monkeypatch.setenv(name, value)


SLURM = {
    "SLURM_JOB_ID": "4711",
    "SLURM_STEP_NODELIST": "node[003-004],gpu7",
    "SLURM_NTASKS": "2",
    "SLURM_PROCID": "1",
    "SLURM_LOCALID": "0",
}


def test_srun_is_detected_through_jax(monkeypatch):
  _cluster_env(monkeypatch, **SLURM)
  assert sharding.cluster_launcher() == "slurm"
  # JAX: the first node of the step, port 61440 + job id mod 4096 (4711 % 4096 = 615)
  assert sharding.detect_cluster("slurm") == ("node003:62055", 2, 1, [0])
  monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "10.1.2.3:1234")  # today's variables win
  monkeypatch.setenv("JAX_PROCESS_ID", "0")
  assert sharding.detect_cluster("slurm") == ("10.1.2.3:1234", 2, 0, [0])


def test_mpirun_is_detected_through_jax(monkeypatch):
  _cluster_env(
      monkeypatch,
      OMPI_MCA_orte_hnp_uri="1531576320.0;tcp://10.96.0.1,10.148.0.1:34911",
      OMPI_COMM_WORLD_SIZE="2",
      OMPI_COMM_WORLD_RANK="1",
      OMPI_COMM_WORLD_LOCAL_RANK="1",
  )
  assert sharding.cluster_launcher() == "ompi"
  # JAX: the launcher's first address, port 61440 + (job id // 4096) mod 4096 = 61440 + 1184
  assert sharding.detect_cluster("ompi") == ("10.96.0.1:62624", 2, 1, [1])


def test_kubernetes_indexed_job_is_detected_through_jax(monkeypatch):
  from types import ModuleType
  from types import SimpleNamespace as NS

  from jax._src.clusters import k8s_cluster

  pod = NS(
      metadata=NS(
          name="train-1-x7",
          labels={"job-name": "train"},
          owner_references=[NS(controller=True, kind="Job")],
      ),
      spec=NS(subdomain="jaxpods"),
  )
  job = NS(metadata=NS(name="train", labels={}), spec=NS(parallelism=2))
  client = NS(
      CoreV1Api=lambda: NS(list_namespaced_pod=lambda **_: NS(items=[pod])),
      BatchV1Api=lambda: NS(read_namespaced_job=lambda **_: job),
      exceptions=NS(ApiException=RuntimeError),
  )
  fake = ModuleType("kubernetes")
  fake.config, fake.client = NS(load_incluster_config=lambda: None), client
  monkeypatch.setitem(sys.modules, "kubernetes", fake)
  monkeypatch.setattr(k8s_cluster.K8sCluster, "_namespace", classmethod(lambda cls: "default"))
  monkeypatch.setattr(socket, "gethostbyname", lambda host: "10.0.0.5")
  _cluster_env(
      monkeypatch,
      KUBERNETES_SERVICE_HOST="10.0.0.1",
      JOB_COMPLETION_INDEX="1",
      HOSTNAME="train-1-x7",
  )
  try:
    assert sharding.cluster_launcher() == "k8s"
    # JAX: pod 0 of the job under the job's subdomain, its fixed port 55527
    assert sharding.detect_cluster("k8s") == ("train-0.jaxpods:55527", 2, 1, None)
  finally:
    for name in ("_pod", "_job", "_controller", "_headless_svc"):
      getattr(k8s_cluster.K8sCluster, name).__func__.cache_clear()


@pytest.mark.parametrize(
    "env",
    [
        {},
        {**SLURM, "SLURM_NTASKS": "1"},
        {"OMPI_MCA_orte_hnp_uri": "1.0;tcp://h:1", "OMPI_COMM_WORLD_SIZE": "1"},
        {"KUBERNETES_SERVICE_HOST": "10.0.0.1"},
    ],
)
def test_a_process_started_alone_is_no_cluster(env):
  assert sharding.cluster_launcher(env) is None  # initialize_distributed does nothing


def _checkpoint(workdir, step: int) -> np.ndarray:
  """Every leaf of a toy run's checkpoint `step`, as one float64 vector."""
  init_fn, _ = toy.make_task()
  rep = sharding.replicated(sharding.data_mesh())
  abstract = jax.tree.map(
      lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep),
      jax.eval_shape(init_fn, jax.random.key(0)),
  )
  ckpts = checkpointing.Checkpoints(Path(workdir) / "checkpoints", writable=False)
  state, _ = ckpts.load(step, abstract)
  return np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree.leaves(state)])


def _mpirun(workdir, processes: int, **args) -> subprocess.Popen:
  env = environ(XLA_FLAGS="--xla_force_host_platform_device_count=1", JAX_PLATFORMS="cpu")
  env = {
      k: v
      for k, v in env.items()
      if not k.startswith(("JAX_NUM", "JAX_PROCESS_ID", "JAX_COORD", "OMPI_"))
  }
  cmd = [
      "mpirun",
      "--allow-run-as-root",
      "--oversubscribe",
      "-np",
      str(processes),
      "-x",
      "XLA_FLAGS",
      "-x",
      "JAX_PLATFORMS",
      "-x",
      "PYTHONPATH",
      sys.executable,
      str(JOB),
      f"--workdir={workdir}",
  ] + [f"--{k}={v}" for k, v in args.items()]
  return subprocess.Popen(cmd, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("mpirun") is None,
    reason="needs Open MPI's mpirun " "(make test-slow installs openmpi-bin)",
)
def test_mpirun_without_variables_gives_the_checkpoints_of_the_jax_variables_run(tmp_path):
  mpi = _finish([_mpirun(tmp_path / "mpi", 2, epochs=3)])[0]
  assert mpi[0] == 0, mpi[2][-2000:]
  outs = sorted(
      (json.loads(line) for line in mpi[1].splitlines() if line.startswith("{")),
      key=lambda r: r["process"],
  )
  ref = _results(_launch(tmp_path / "vars", 2, epochs=3))
  assert [r["devices"] for r in outs] == [2, 2] and [r["process"] for r in outs] == [0, 1]
  np.testing.assert_array_equal(outs[0]["params"], ref[0]["params"])
  assert outs[0]["loss"] == ref[0]["loss"]
  for step in (2, 3):  # every leaf: parameters, optimiser state, step
    np.testing.assert_array_equal(
        _checkpoint(tmp_path / "mpi", step), _checkpoint(tmp_path / "vars", step)
    )
  assert sorted(p.name for p in (tmp_path / "mpi" / "checkpoints").iterdir()) == ["2", "3"]


# ------------------------------------------------------ a dead peer, preemption, workdirs

PEER_LOST_BOUND_S = 60  # the survivor's exit after its peer's SIGKILL (measured: see docs)


def _error_lines(stderr: str) -> list[str]:
  """stderr without the progress bar's updates and blank lines."""
  lines = (line.strip() for line in stderr.replace("\r", "\n").splitlines())
  return [line for line in lines if line and not line.startswith("train:")]


@pytest.mark.slow
@pytest.mark.parametrize("victim", [0, 1])
def test_a_killed_peer_stops_the_other_within_the_bound(tmp_path, victim):
  procs = _launch(tmp_path, 2, epochs=200, sleep=0.2)
  _wait_for_line(procs[victim], "epoch 3")
  procs[victim].send_signal(signal.SIGKILL)
  killed, survivor = time.monotonic(), procs[1 - victim]
  try:
    _, err = survivor.communicate(timeout=PEER_LOST_BOUND_S + 30)
  finally:
    _finish(procs)
  took = time.monotonic() - killed
  assert survivor.returncode != 0 and took < PEER_LOST_BOUND_S, (took, err[-3000:])
  ckpts = checkpointing.Checkpoints(tmp_path / "checkpoints", writable=False)
  assert ckpts.latest_epoch >= 2
  init_fn, _ = toy.make_task()
  toy.restore(tmp_path, init_fn)  # the last complete step loads
  # process 0 too: the coordination service lives on in its child (distributed.coordination)
  lines = _error_lines(err)
  assert survivor.returncode == preemption.PEER_LOST_STATUS, err[-3000:]
  assert (
      len(lines) == 1
      and lines[0].startswith("toy_job: error: ")
      and "another process of this 2-process run probably died" in lines[0]
  ), lines
  assert f"checkpoint is epoch {ckpts.latest_epoch} in" in lines[0]


@pytest.mark.slow
def test_sigterm_to_every_process_saves_and_the_requeue_ends_bit_identical(tmp_path):
  reference = _results(_launch(tmp_path / "ref", 2, epochs=4))[0]
  procs = _launch(tmp_path / "run", 2, epochs=4, sleep=1.0)
  for p in procs:
    _wait_for_line(p, "epoch 1")
  for p in procs:  # the scheduler preempts the job
    p.send_signal(signal.SIGTERM)
  done = _finish(procs)
  assert [code for code, _, _ in done] == [143, 143], [err[-2000:] for _, _, err in done]
  assert "stopped: preempted (SIGTERM)" in done[0][2]
  resumed = _results(_launch(tmp_path / "run", 2, epochs=4))  # the requeued job
  np.testing.assert_array_equal(resumed[0]["params"], reference["params"])
  np.testing.assert_array_equal(resumed[1]["params"], reference["params"])
  ref_lines = (tmp_path / "ref" / "metrics.jsonl").read_text().splitlines()
  lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
  assert [json.loads(line)["loss"] for line in lines] == [
      json.loads(line)["loss"] for line in ref_lines
  ]


@pytest.mark.slow
def test_processes_given_other_workdirs_are_refused_up_front(tmp_path):
  done = _finish(_launch(tmp_path / "a", 2, epochs=1, own=[{}, {"workdir": tmp_path / "b"}]))
  assert [code for code, _, _ in done] == [2, 2]
  for _, _, err in done:
    assert "workdir: process 1" in err.strip().splitlines()[-1], err[-2000:]
  assert not (tmp_path / "a" / "checkpoints").exists()
  assert not (tmp_path / "b" / "checkpoints").exists()
