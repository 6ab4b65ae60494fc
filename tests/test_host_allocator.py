"""The entry points' allocator choice (`cvmdx_jax.host_allocator`), the re-execution, and
their check of the performance options' variables (`cvmdx_jax.models.performance`)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from cvmdx_jax import host_allocator as ha
from tests.subprocess_env import pythonpath

REPO = Path(__file__).resolve().parents[1]
JE = "/opt/lib/libjemalloc.so.2"


def test_jemalloc_preferred_and_existing_settings_kept():
  env = ha.allocator_environment(
      {"LD_PRELOAD": "/x/a.so", "MALLOC_CONF": "narenas:2", "K": "v"},
      "linux",
      exists=lambda p: p == ha.JEMALLOC_PATHS[0],
  )
  assert env["LD_PRELOAD"] == f"{ha.JEMALLOC_PATHS[0]}:/x/a.so"
  assert env["MALLOC_CONF"] == "dirty_decay_ms:-1,muzzy_decay_ms:-1,narenas:2"
  assert env[ha.APPLIED] == "1" and env["K"] == "v" and "GLIBC_TUNABLES" not in env


def test_glibc_tunables_without_jemalloc():
  env = ha.allocator_environment(
      {"GLIBC_TUNABLES": "glibc.cpu.x86_shstk=on"}, "linux", exists=lambda p: False
  )
  assert env["GLIBC_TUNABLES"].split(":") == [
      "glibc.malloc.mmap_max=0",
      "glibc.malloc.trim_threshold=68719476736",
      "glibc.malloc.hugetlb=1",
      "glibc.cpu.x86_shstk=on",
  ]
  assert "LD_PRELOAD" not in env


def test_explicit_jemalloc_path():
  env = ha.allocator_environment({ha.JEMALLOC_ENV: JE}, "linux", exists=lambda p: p == JE)
  assert env["LD_PRELOAD"] == JE
  with pytest.raises(ValueError, match=ha.JEMALLOC_ENV):
    ha.allocator_environment({ha.JEMALLOC_ENV: JE}, "linux", exists=lambda p: False)


@pytest.mark.parametrize(
    "environ, platform",
    [({ha.OPT_OUT: "system"}, "linux"), ({ha.APPLIED: "1"}, "linux"), ({}, "darwin")],
)
def test_left_alone(environ, platform):
  assert ha.allocator_environment(environ, platform, exists=lambda p: True) is None


def test_bad_choice_named():
  with pytest.raises(ValueError, match="CVMDX_ALLOCATOR='jemaloc': expected one of auto, "):
    ha.allocator_environment({ha.OPT_OUT: "jemaloc"}, "linux")


@pytest.mark.parametrize(
    "platforms, accelerator",
    [
        ("", False),
        ("cpu", False),
        ("cpu,cuda", False),
        ("cuda", True),
        (" gpu , cpu", True),
        ("tpu", True),
    ],
)
def test_auto_leaves_an_accelerator_process_alone(platforms, accelerator):
  environ = {"JAX_PLATFORMS": platforms}
  assert ha.accelerator_requested(environ) is accelerator
  for choice in ("", "auto"):
    env = ha.allocator_environment({**environ, ha.OPT_OUT: choice}, "linux", exists=lambda p: False)
    assert (env is None) is accelerator
  # an explicit choice holds on any platform
  env = ha.allocator_environment({**environ, ha.OPT_OUT: "glibc"}, "linux", exists=lambda p: False)
  assert ha.in_force(env) == "glibc tunables"


def test_explicit_choices():
  je = lambda p: p == JE
  env = ha.allocator_environment({ha.OPT_OUT: "glibc", ha.JEMALLOC_ENV: JE}, "linux", exists=je)
  assert "LD_PRELOAD" not in env and ha.in_force(env) == "glibc tunables"
  env = ha.allocator_environment({ha.OPT_OUT: "jemalloc", ha.JEMALLOC_ENV: JE}, "linux", exists=je)
  assert env["LD_PRELOAD"] == JE and ha.in_force(env) == "jemalloc"
  with pytest.raises(ValueError, match="CVMDX_ALLOCATOR=jemalloc: libjemalloc.so.2 is not"):
    ha.allocator_environment({ha.OPT_OUT: "jemalloc"}, "linux", exists=lambda p: False)
  assert ha.in_force({}) == "system"


_SCRIPT = """
import os
from cvmdx_jax import cli
print("start", os.environ.get("CVMDX_ALLOCATOR_APPLIED"), flush=True)  # once per process
def main(argv):
  print(os.environ.get("CVMDX_ALLOCATOR_APPLIED"), os.environ.get("GLIBC_TUNABLES"), argv[1:])
cli.run(main, allocator={allocator})
"""


def _entry_point(tmp_path, allocator: bool):
  """Runs a `cli.run` entry point with extra environment and arguments -> CompletedProcess."""
  script = tmp_path / f"entry_{allocator}.py"
  script.write_text(_SCRIPT.format(allocator=allocator))
  env = {k: v for k, v in os.environ.items() if k not in (ha.OPT_OUT, ha.APPLIED, "GLIBC_TUNABLES")}
  env.update(PYTHONPATH=pythonpath(), CVMDX_JEMALLOC="", JAX_PLATFORMS="cpu")
  return lambda *argv, **extra: subprocess.run(
      [sys.executable, str(script), *argv],
      capture_output=True,
      text=True,
      env={**env, **extra},
      timeout=120,
  )


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the re-execution is Linux only")
def test_training_entry_point_reexecutes_once_with_its_arguments(tmp_path):
  run = _entry_point(tmp_path, allocator=True)
  proc = run("a", "b")  # jemalloc where installed, else the glibc tunables
  assert proc.returncode == 0, proc.stderr
  lines = proc.stdout.splitlines()
  assert lines[:2] == ["start None", "start 1"] and len(lines) == 3
  assert lines[2].startswith("1 ") and lines[2].endswith("['a', 'b']")
  proc = run("a", "b", **{ha.OPT_OUT: "system"})
  assert proc.stdout.splitlines() == ["start None", "None None ['a', 'b']"]
  proc = run(**{ha.OPT_OUT: "bogus"})
  assert proc.returncode == 2 and "error: CVMDX_ALLOCATOR='bogus'" in proc.stderr


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the re-execution is Linux only")
@pytest.mark.parametrize("help_flag", ["--help", "--helpfull", "-?"])
def test_help_of_a_training_entry_point_does_not_reexecute(tmp_path, help_flag):
  proc = _entry_point(tmp_path, allocator=True)(help_flag)  # absl: usage, exit status 1
  assert proc.stdout.splitlines()[0] == "start None"
  assert "start 1" not in proc.stdout and "USAGE" in proc.stdout


def test_other_entry_points_do_not_reexecute(tmp_path):
  proc = _entry_point(tmp_path, allocator=False)("a", "b")
  assert proc.returncode == 0, proc.stderr
  assert proc.stdout.splitlines() == ["start None", "None None ['a', 'b']"]


@pytest.mark.parametrize("variable", ["CVMDX_WINOGRAD", "CVMDX_GROUP_NORM_BACKWARD"])
def test_entry_points_refuse_a_bad_performance_option(tmp_path, variable):
  proc = _entry_point(tmp_path, allocator=True)(**{variable: "fast"})
  assert proc.returncode == 2 and proc.stdout.splitlines() == ["start None"]  # not re-executed
  assert proc.stderr.strip().endswith(
      f"error: {variable}='fast': expected one of auto, on, off"
  ), proc.stderr
