"""Signals and hostile config files at the entry points (`cli.run`): SIGTERM prints one
line and exits 143 after removing temporary directories and killing child processes (the
SUMO simulations of make_dataset); SIGINT in a process running JAX exits 130 without a
crash at interpreter exit; a config file that cannot be loaded is one line."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[1]


def _procs_with(marker: str) -> list[int]:
  """Pids of the processes whose command line holds `marker`."""
  found = []
  for entry in Path("/proc").iterdir():
    try:
      if entry.name.isdigit() and marker in (entry / "cmdline").read_bytes().decode(
          errors="replace"
      ):
        found.append(int(entry.name))
    except OSError:  # ended meanwhile
      continue
  return found


def _start(argv: list[str], tmp_path: Path, **env) -> subprocess.Popen:
  # SIGINT as in a terminal: a parent that ignores it would pass the ignore on
  return subprocess.Popen(
      argv,
      cwd=REPO,
      env=environ(JAX_PLATFORMS="cpu", **env),
      stdout=subprocess.PIPE,
      stderr=subprocess.PIPE,
      text=True,
      preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
  )


_SLEEPER = """
import os, sys, tempfile, time
from cvmdx_jax import cli
from cvmdx_jax.data import sumo_network
def main(argv):
  with tempfile.TemporaryDirectory(prefix="sleeper_") as tmp:
    print('ready', flush=True)
    if argv[1:] == ['starting']:  # the signal comes while the child starts: Popen waits for
      read = os.read              # its exec on a pipe, made here to take 3 s more
      os.read = lambda fd, n: (setattr(os, 'read', read), time.sleep(3), read(fd, n))[2]
    # a child whose command line names the directory
    sumo_network.run_program([sys.executable, '-c', 'import time; time.sleep(300)', tmp])
cli.run(main)
"""


# The sleeper's child used to outlive a SIGTERM that came while subprocess.run was still in
# Popen's constructor (after the child's exec): it held the test's pipes, and `communicate`
# hung (intermittently, under load). `sumo_network.run_program` holds the signal until the
# child is started, kills it, then raises the signal again.
@pytest.mark.parametrize("when", ["running", "starting"])
def test_sigterm_is_one_line_143_and_leaves_no_temporary_directory_or_child(tmp_path, when):
  script = tmp_path / "sleeper.py"
  script.write_text(_SLEEPER)
  temp = tmp_path / "temp"
  temp.mkdir()
  proc = _start([sys.executable, str(script), when], tmp_path, TMPDIR=str(temp))
  try:
    assert proc.stdout.readline() == "ready\n"
    deadline = time.monotonic() + 60  # the child has started (slow on a loaded machine)
    while not _procs_with(str(temp)) and time.monotonic() < deadline:
      time.sleep(0.05)
    assert _procs_with(str(temp)), "the sleeper's child did not start"
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
  finally:
    proc.kill()
    proc.communicate()  # closes the pipes
  assert proc.returncode == 143, stderr
  assert stderr == "sleeper: error: terminated; rerun to resume\n"
  assert list(temp.iterdir()) == []
  left = _procs_with(str(temp))
  assert left == [], [Path(f"/proc/{p}/status").read_text()[:300] for p in left] + [
      Path(f"/proc/{p}/cmdline").read_bytes() for p in left
  ]


_JAX_WORKER = """
import jax, jax.numpy as jnp
from cvmdx_jax import cli
from cvmdx_jax.storage import checkpointing
def main(argv):
  with checkpointing.Checkpoints(argv[1]) as ckpts:
    x = jnp.ones((256, 256))
    ckpts.save(1, {'x': x}, {'q': 1})
    step = jax.jit(lambda x: jnp.tanh(x @ x) / 256)
    print('ready', flush=True)
    while True:
      x = step(x).block_until_ready()
cli.run(main)
"""


def _interrupt_jax_worker(tmp_path: Path, index: int) -> tuple[int, str]:
  script = tmp_path / "jax_worker.py"
  script.write_text(_JAX_WORKER)
  proc = _start([sys.executable, str(script), str(tmp_path / f"ckpt{index}")], tmp_path)
  try:
    assert proc.stdout.readline() == "ready\n"
    time.sleep(0.5 + 0.3 * index)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
  finally:
    proc.kill()
  return proc.returncode, stderr


def test_sigint_while_jax_and_orbax_run_exits_130(tmp_path):
  rc, stderr = _interrupt_jax_worker(tmp_path, 0)
  assert rc == 130, stderr
  assert stderr.splitlines()[-1] == "jax_worker: error: interrupted; rerun to resume"


@pytest.mark.slow
def test_sigint_while_jax_and_orbax_run_exits_130_every_time(tmp_path):
  results = [_interrupt_jax_worker(tmp_path, i) for i in range(8)]
  assert [rc for rc, _ in results] == [130] * 8, results


@pytest.mark.slow
def test_sigterm_during_make_dataset_stops_sumo_and_cleans_up(tmp_path):
  temp, data = tmp_path / "temp", tmp_path / "data"
  temp.mkdir()
  proc = _start(
      [
          sys.executable,
          "experiments/make_dataset.py",
          "--config=configs/dataset.py:tiny",
          f"--data_dir={data}",
      ],
      tmp_path,
      TMPDIR=str(temp),
  )
  try:
    for _ in range(1200):  # SUMO runs (its command line names the temporary directory)
      if any(p != proc.pid for p in _procs_with(str(temp))) or proc.poll() is not None:
        break
      time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
  finally:
    proc.kill()
  lines = [s for s in stderr.splitlines() if s.startswith("make_dataset")]
  assert proc.returncode == 143, stderr
  assert lines == ["make_dataset: error: terminated; rerun to resume"], stderr
  time.sleep(1.0)
  assert _procs_with(str(temp)) == [] and list(temp.iterdir()) == []
  assert not (data / "cache" / "metadata.json").exists()


@pytest.mark.parametrize(
    "text, named",
    [
        ("def get_config(:\n", "SyntaxError: invalid syntax"),
        pytest.param("x = 1\n", "has no attribute 'get_config'", marks=pytest.mark.slow),
        pytest.param(
            '{"model": {"num_heads": 3}}\n', "has no attribute 'get_config'", marks=pytest.mark.slow
        ),  # a run's config.json
    ],
)
def test_a_config_file_that_cannot_be_loaded_is_one_line(tmp_path, text, named):
  config = tmp_path / ("config.json" if text.startswith("{") else "config.py")
  config.write_text(text)
  proc = subprocess.run(
      [
          sys.executable,
          "experiments/train_diffusion.py",
          f"--config={config}",
          f"--workdir={tmp_path / 'new'}",
      ],
      cwd=REPO,
      env=environ(JAX_PLATFORMS="cpu"),
      capture_output=True,
      text=True,
      timeout=300,
  )
  lines = [s for s in proc.stderr.splitlines() if s.strip()]
  assert proc.returncode == 2 and len(lines) == 1, proc.stderr
  assert lines[0].startswith(f"train_diffusion: error: --config={config}") and named in lines[0]
  assert not (tmp_path / "new").exists()
