"""Run directories are owned by one process (cvmdx_jax.storage.locking and where it is wired in)."""

import fcntl
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from configs import dataset as dataset_config
from configs import diffusion as diffusion_config
from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.runs import DiffusionRunConfig, TokenizerRunConfig
from cvmdx_jax.data import dataset
from cvmdx_jax.evaluation import report
from cvmdx_jax.storage import locking
from cvmdx_jax.train import diffusion, tokenizer
from tests.subprocess_env import environ
from tests.train import toy

REPO = Path(__file__).resolve().parents[2]
_HOLDER = (
    "import sys, time\nfrom cvmdx_jax.storage import locking\n"
    "with locking.hold(sys.argv[1]):\n  print('held', flush=True)\n  time.sleep(600)\n"
)


@pytest.fixture
def holder():
  """Starts a process that holds a workdir's lock until killed; yields a start function."""
  procs = []

  def start(workdir):
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLDER, str(workdir)],
        text=True,
        stdout=subprocess.PIPE,
        env=environ(),
    )
    procs.append(proc)
    assert proc.stdout.readline().strip() == "held"
    return proc

  yield start
  for proc in procs:
    proc.kill()
    proc.wait()
    proc.stdout.close()


def _snapshot(root: Path) -> dict:
  """{relative path: (bytes, mtime_ns)} of every file under root, and every directory."""
  return {
      str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns) if p.is_file() else "dir"
      for p in root.rglob("*")
  }


def test_second_process_is_refused_naming_the_pid_and_sigkill_frees_the_lock(tmp_path, holder):
  proc = holder(tmp_path / "run")
  assert (tmp_path / "run" / ".lock").read_text().split()[0] == str(proc.pid)
  with pytest.raises(locking.WorkdirLockedError, match=f"pid {proc.pid} ") as err:
    with locking.hold(tmp_path / "run"):
      pass
  assert isinstance(err.value, ValueError)  # the entry points' runner: "error: ...", exit 2
  proc.send_signal(signal.SIGKILL)
  proc.wait()
  with locking.hold(tmp_path / "run") as path:  # no stale lock: the OS dropped it
    assert path.read_text().split()[0] == str(os.getpid())


def test_refused_training_leaves_the_run_byte_identical(tmp_path, holder):
  init_fn, step_fn = toy.make_task()
  args = dict(
      workdir=tmp_path,
      init_fn=init_fn,
      step_fn=step_fn,
      data=toy.make_data(20),
      batch_size=4,
      seed=0,
      fingerprint={"toy": 1},
  )
  toy.train(num_epochs=1, **args)
  before = _snapshot(tmp_path)
  proc = holder(tmp_path)
  before[".lock"] = _snapshot(tmp_path)[".lock"]  # now names the holder
  with pytest.raises(locking.WorkdirLockedError, match=str(proc.pid)):
    toy.train(num_epochs=3, **args)  # would append to metrics.jsonl and checkpoint
  assert _snapshot(tmp_path) == before


def _tokenizer(workdir):
  tokenizer.train(TokenizerRunConfig.from_config(tokenizer_config.get_config("tiny")), workdir)


def _diffusion(workdir):
  diffusion.train(DiffusionRunConfig.from_config(diffusion_config.get_config("tiny")), workdir)


def _dataset(workdir):
  dataset.build(dataset_config.get_config("small"), workdir)


def _evaluation(workdir):
  report.run(
      tokenizer_dir=workdir / "t",
      diffusion_dir=workdir / "d",
      data_dir=workdir / "x",
      workdir=workdir,
  )


@pytest.mark.parametrize("command", [_tokenizer, _diffusion, _dataset, _evaluation])
def test_every_writing_command_locks_its_workdir_before_writing(tmp_path, holder, command):
  (tmp_path / "metrics.jsonl").write_text("{}\n")
  proc = holder(tmp_path)
  before = _snapshot(tmp_path)
  with pytest.raises(locking.WorkdirLockedError, match=str(proc.pid)):
    command(tmp_path)
  assert _snapshot(tmp_path) == before


def test_evaluate_script_answers_a_locked_workdir_with_one_line_and_exit_2(tmp_path, holder):
  proc = holder(tmp_path / "eval")
  out = subprocess.run(
      [
          sys.executable,
          str(REPO / "experiments" / "evaluate.py"),
          f"--tokenizer_dir={tmp_path}",
          f"--diffusion_dir={tmp_path}",
          f"--data_dir={tmp_path}",
          f"--workdir={tmp_path}/eval",
      ],
      capture_output=True,
      text=True,
      timeout=300,
      env=environ(JAX_PLATFORMS="cpu"),
  )
  assert out.returncode == 2
  assert out.stderr.startswith("evaluate: error: workdir ") and f"pid {proc.pid}" in out.stderr
  assert "Traceback" not in out.stderr


def test_holds_nest_in_one_process_and_are_released(tmp_path):
  with locking.hold(tmp_path) as path:
    with locking.hold(tmp_path):  # a nested hold of the same process
      pass
    fd = os.open(path, os.O_RDWR)  # still held by the outer block: another fd is refused
    try:
      with pytest.raises(BlockingIOError):
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    finally:
      os.close(fd)
  with locking.hold(tmp_path):
    pass


def test_a_refused_run_leaves_no_directory_it_created(tmp_path):
  with pytest.raises(ZeroDivisionError):
    with locking.hold(tmp_path / "new" / "run"):
      1 / 0
  assert not (tmp_path / "new" / "run").exists()
  with locking.hold(tmp_path / "kept"):
    (tmp_path / "kept" / "result").write_text("x")
  assert sorted(p.name for p in (tmp_path / "kept").iterdir()) == [".lock", "result"]


def test_uncreatable_workdir_is_a_clear_value_error(tmp_path):
  (tmp_path / "file").write_text("")
  with pytest.raises(locking.WorkdirError, match="file/run: cannot create its lock file"):
    with locking.hold(tmp_path / "file" / "run"):
      pass
