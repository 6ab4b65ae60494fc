"""Entry points: a user's mistake gives one line `<script>: error: <message>` naming the
flag, file or field, exit status 2 and no traceback, before any work is done.

Each case runs the script in a subprocess (`JAX_PLATFORMS=cpu`), about 2-3 s each: every
script gets an unknown flag, a bad value of a numeric flag or config field, a missing
input directory and, where it has a config, a bad preset or field; the other kinds of
user error (unwritable output directory, garbled JSON, locked workdir, missing dataset,
wrong type, NaN, missing config file, missing required flag, stray argument) once each.
The default run takes each script's first case and each of those kinds; the rest are slow.
"""

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from configs import diffusion as diffusion_config
from cvmdx_jax import cli
from cvmdx_jax.data.errors import DataError
from cvmdx_jax.errors import UserError
from cvmdx_jax.storage import atomic, locking
from tests.subprocess_env import environ

REPO = Path(__file__).resolve().parents[1]
# absl INFO lines (a script may log its devices before it fails): not error output
_INFO = re.compile(r"^I\d{4} \d\d:\d\d:\d\d")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
  """{T}: an empty directory, a plain file, a dataset directory with a garbled
  recordings/plans.json and a directory whose lock this process holds."""
  root = tmp_path_factory.mktemp("cli")
  (root / "empty").mkdir()
  (root / "file").write_text("not a directory\n")
  (root / "garbled" / "recordings").mkdir(parents=True)
  (root / "garbled" / "recordings" / "plans.json").write_text('{"1": {"split": "tr')
  with locking.hold(root / "locked"):
    yield root


# (script, arguments, text the error line must contain); {T} is the `inputs` directory,
# {NEW} a fresh path that must still not exist afterwards.
TOK = "--config=configs/tokenizer.py:tiny"
DIFF = "--config=configs/diffusion.py:tiny"
DATA = "--config=configs/dataset.py:tiny"
EVAL = "--tokenizer_dir={T}/empty --diffusion_dir={T}/empty --data_dir={T}/empty"
BASE = "--config=configs/baseline.py:tiny"
MDN = "--config=configs/mdn.py:tiny"
DIST = "--config=configs/distill.py:tiny"
LONG = "n" * 300  # a path component longer than any file system allows (ENAMETOOLONG)
CASES = [
    ("ablate_codebook", "--data_dir={T}/empty --workdir={NEW} --nosuch=1", "'nosuch'"),
    ("ablate_codebook", "--data_dir={T}/nosuch --workdir={NEW}", "--data_dir="),
    (
        "ablate_codebook",
        "--data_dir={T}/empty --workdir={NEW} --max_scenarios=-1",
        "--max_scenarios=-1",
    ),
    (
        "ablate_codebook",
        "--data_dir={T}/empty --workdir={NEW} --diffusion_preset=nosuch",
        "--diffusion_preset=nosuch",
    ),
    ("benchmark", "--nosuch=1", "'nosuch'"),
    ("benchmark", "--repeats=0", "--repeats=0"),
    ("benchmark", "--performance=fast", "--performance"),
    ("benchmark_sampling", "--nosuch=1", "'nosuch'"),
    ("benchmark_sampling", "--num_samples=2", "--num_samples=2"),
    ("benchmark_costs", "--workdir={NEW} --nosuch=1", "'nosuch'"),
    ("benchmark_quality", "--workdir={NEW} --nosuch=1", "'nosuch'"),
    ("benchmark_stack", "--nosuch=1", "'nosuch'"),
    ("calibrate_probs", f"{EVAL} --nosuch=1", "'nosuch'"),
    (
        "calibrate_probs",
        "--tokenizer_dir={T}/nosuch --diffusion_dir={T}/empty --data_dir={T}/empty",
        "--tokenizer_dir=",
    ),
    ("calibrate_probs", f"{EVAL} --max_scenarios=-1", "--max_scenarios=-1"),
    ("codebook_health", f"{TOK} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    (
        "codebook_health",
        "--config=configs/tokenizer.py:nosuch --workdir={NEW}",
        "--config=configs/tokenizer.py:nosuch",
    ),
    (
        "codebook_health",
        f"{TOK} --config.data_dir={{T}}/nosuch --workdir={{NEW}}",
        "--config.data_dir=",
    ),
    (
        "codebook_health",
        f"{TOK} --config.data_dir={{T}}/empty --workdir={{NEW}} " "--codebook_sizes=0",
        "--codebook_sizes=",
    ),
    (
        "codebook_health",
        f"{TOK} --config.data_dir={{T}}/empty --workdir={{NEW}}",
        "empty/cache/metadata.json",
    ),  # no dataset there
    ("distill", f"{DIST} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    (
        "distill",
        f"{DIST} --workdir={{NEW}} --config.teacher_dir={{T}}/nosuch",
        "--config.teacher_dir=",
    ),
    (
        "distill",
        f"{DIST} --workdir={{NEW}} --config.teacher_dir={{T}}/empty " "--config.steps=0",
        "--config.steps=0",
    ),
    (
        "distill",
        f"{DIST} --workdir={{NEW}} --config.teacher_dir={{T}}/empty",
        "empty/config.json",
    ),  # not a run directory
    ("evaluate", f"{EVAL} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    (
        "evaluate",
        "--tokenizer_dir={T}/nosuch --diffusion_dir={T}/empty "
        "--data_dir={T}/empty --workdir={NEW}",
        "--tokenizer_dir=",
    ),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --max_scenarios=-5", "--max_scenarios=-5"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --seed=4294967296", "--seed=4294967296"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --sampler=euler", "--sampler=euler"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --steps=0", "--steps=0"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --prob_temperature=0", "--prob_temperature=0"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --intent_prior=1,2", "--intent_prior=1,2"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --intent_prior=0,1,1", "--intent_prior=0,1,1"),
    ("evaluate", f"{EVAL} --workdir={{NEW}} --intent_prior=a,1,1", "--intent_prior=a,1,1"),
    ("evaluate", f"{EVAL} --workdir={{T}}/file/sub", "--workdir="),  # not writable
    ("evaluate", f"{EVAL} --workdir={{NEW}} --baseline_dir={{T}}/nosuch", "--baseline_dir="),
    ("evaluate", f"{EVAL} --workdir={{T}}/{LONG}/sub", "File name too long"),
    (
        "evaluate",
        f"--tokenizer_dir={{T}}/{LONG} --diffusion_dir={{T}}/empty "
        "--data_dir={T}/empty --workdir={NEW}",
        "File name too long",
    ),
    (
        "export",
        "--tokenizer_dir={T}/nosuch --diffusion_dir={T}/empty --out={NEW}",
        "--tokenizer_dir=",
    ),
    ("hypothesis_sweep", "--out_dir={NEW} --nosuch=1", "'nosuch'"),
    ("hypothesis_sweep", "--out_dir={NEW} --num_scenarios=-1", "--num_scenarios=-1"),
    ("hypothesis_sweep", f"{EVAL} --out_dir={{NEW}} --tolerance=-0.1", "--tolerance=-0.1"),
    ("hypothesis_sweep", "--out_dir={NEW} --num_samples=9,1000000", "--num_samples="),
    ("import_official", "--checkpoint={T}/file --workdir={NEW} --nosuch=1", "'nosuch'"),
    (
        "import_official",
        "--checkpoint={T}/file --workdir={NEW} --tokenizer_dir={T}/nosuch",
        "--tokenizer_dir=",
    ),
    ("import_official", "--checkpoint={T}/nosuch.pt --workdir={NEW}", "--checkpoint="),
    ("import_official", "--checkpoint={T}/file --workdir={NEW} --num_heads=0", "--num_heads=0"),
    ("make_dataset", f"{DATA} --data_dir={{NEW}} --nosuch=1", "'nosuch'"),
    ("make_dataset", f"{DATA} --data_dir={{NEW}} --config.nosuch=1", "--config.nosuch"),
    (
        "make_dataset",
        f"{DATA} --data_dir={{NEW}} --config.sumo.workers=two",
        "--config.sumo.workers=two",
    ),  # wrong type
    (
        "make_dataset",
        f"{DATA} --data_dir={{NEW}} --config.sumo.duration_s=-60",
        "--config.sumo.duration_s=-60",
    ),
    (
        "make_dataset",
        f"{DATA} --data_dir={{NEW}} --config.source=highd " "--config.highd_dir={T}/nosuch",
        "--config.highd_dir=",
    ),
    ("make_dataset", f"{DATA} --data_dir={{T}}/locked", "pid"),  # WorkdirLockedError
    (
        "predict_recording",
        "--tokenizer_dir={T}/empty --diffusion_dir={T}/empty "
        "--recording={T}/file --out={NEW}/p.csv.gz --nosuch=1",
        "'nosuch'",
    ),
    (
        "predict_recording",
        "--tokenizer_dir={T}/nosuch --diffusion_dir={T}/empty "
        "--recording={T}/file --out={NEW}/p.csv.gz",
        "--tokenizer_dir=",
    ),
    (
        "predict_recording",
        "--tokenizer_dir={T}/empty --diffusion_dir={T}/empty "
        "--recording={T}/file --out={NEW}/p.csv.gz",
        "NN_tracks.csv",
    ),
    (
        "predict_recording",
        "--tokenizer_dir={T}/empty --diffusion_dir={T}/empty "
        "--recording={T}/file --out={NEW}/p.csv.gz --every=0",
        "--every=0",
    ),
    ("recording_stats", "--data_dir={T}/empty --nosuch=1", "'nosuch'"),
    ("recording_stats", "--data_dir={T}/nosuch", "--data_dir="),
    ("recording_stats", "--data_dir={T}/garbled", "recordings/plans.json"),  # bad JSON
    (
        "region_groups",
        "--run={T}/empty --data_dir={T}/empty --workdir={NEW} --nosuch=1",
        "'nosuch'",
    ),
    ("region_groups", "--run={T}/nosuch --data_dir={T}/empty --workdir={NEW}", "--run="),
    ("region_groups", "--run={T}/empty --data_dir={T}/empty --workdir={NEW}", "--run: "),
    (
        "region_groups",
        "--run={T}/empty --data_dir={T}/empty --workdir={NEW} --max_scenarios=-1",
        "--max_scenarios=-1",
    ),
    ("sampler_pareto", "--out_dir={NEW} --nosuch=1", "'nosuch'"),
    ("sampler_pareto", "--out_dir={NEW} --num_scenarios=-1", "--num_scenarios=-1"),
    (
        "run_exported",
        "--export_dir={T}/nosuch --inputs={T}/file --out={NEW}/o.npz",
        "nosuch/manifest.json",
    ),
    ("run_demo", "--workdir={NEW} --nosuch=1", "'nosuch'"),
    ("run_demo", "--workdir={NEW} --data_preset=nosuch", "--data_preset=nosuch"),
    ("run_demo", "--workdir={NEW} --ddpm_scenarios=-1", "--ddpm_scenarios=-1"),
    ("run_demo", "--workdir={NEW} --seed=-1", "--seed=-1"),
    ("run_demo", "--workdir={NEW} --ood_ddpm_scenarios=-1", "--ood_ddpm_scenarios=-1"),
    ("train_baseline", f"{BASE} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    (
        "train_baseline",
        "--config=configs/baseline.py:nosuch --workdir={NEW}",
        "--config=configs/baseline.py:nosuch",
    ),
    (
        "train_baseline",
        f"{BASE} --workdir={{NEW}} --config.data_dir={{T}}/empty "
        "--config.tokenizer_dir={T}/empty --config.train.end_lr_fraction=2",
        "--config.train.end_lr_fraction=2",
    ),
    (
        "train_baseline",
        f"{BASE} --workdir={{NEW}} --config.data_dir={{T}}/empty "
        "--config.tokenizer_dir={T}/empty --config.train.select_metric=accuracy",
        "train.select_metric",
    ),
    (
        "train_mdn",
        f"{MDN} --workdir={{NEW}} --config.data_dir={{T}}/empty "
        "--config.tokenizer_dir={T}/empty --config.model.std_floor_m=0",
        "--config.model.std_floor_m=0",
    ),
    ("train_mdn", f"{MDN} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    ("train_diffusion", f"{DIFF} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    (
        "train_diffusion",
        "--config=configs/diffusion.py:nosuch --workdir={NEW}",
        "--config=configs/diffusion.py:nosuch",
    ),
    ("train_diffusion", "--config=configs/nosuch.py --workdir={NEW}", "--config=configs/nosuch.py"),
    (
        "train_diffusion",
        f"{DIFF} --workdir={{NEW}} --config.train.nosuch=1",
        "--config.train.nosuch",
    ),
    (
        "train_diffusion",
        f"{DIFF} --workdir={{NEW}} --config.data_dir={{T}}/nosuch",
        "--config.data_dir=",
    ),
    (
        "train_diffusion",
        f"{DIFF} --workdir={{NEW}} --config.data_dir={{T}}/empty "
        "--config.tokenizer_dir={T}/empty --config.train.num_epochs=-3",
        "--config.train.num_epochs=-3",
    ),
    (
        "train_diffusion",
        f"{DIFF} --workdir={{NEW}} --config.data_dir={{T}}/empty "
        "--config.tokenizer_dir={T}/empty --config.sampling.guidance.w_min=nan",
        "--config.sampling.guidance.w_min=nan",
    ),
    (
        "train_diffusion",
        f"{DIFF} --workdir={{NEW}} --config.data_dir={{T}}/empty "
        "--config.tokenizer_dir={T}/empty --config.diffusion.control_scale=fast",
        "--config.diffusion.control_scale=",
    ),
    ("train_tokenizer", f"{TOK} --workdir={{NEW}} --nosuch=1", "'nosuch'"),
    (
        "train_tokenizer",
        "--config=configs/tokenizer.py:q=sixty --workdir={NEW}",
        "--config=configs/tokenizer.py:q=sixty",
    ),
    (
        "train_tokenizer",
        f"{TOK} --workdir={{NEW}} --config.data_dir={{T}}/nosuch",
        "--config.data_dir=",
    ),
    (
        "train_tokenizer",
        f"{TOK} --workdir={{NEW}} --config.data_dir={{T}}/{LONG}",
        "File name too long",
    ),
    (
        "train_tokenizer",
        f"{TOK} --workdir={{NEW}} --config.data_dir={{T}}/empty " "--config.train.batch_size=0",
        "--config.train.batch_size=0",
    ),
    ("train_tokenizer", "--workdir={NEW}", "--config"),  # required flag missing
    (
        "train_tokenizer",
        f"{TOK} --workdir={{T}}/locked --config.data_dir={{T}}/empty",
        "pid",
    ),  # WorkdirLockedError
    ("train_tokenizer", f"{TOK} --workdir={{NEW}} --config.data_dir={{T}}/empty stray", "stray"),
]


# The default run: each script's first case and each kind of error once (about 2-3 s of
# start-up a case); the other cases run in the slow target.
KINDS = {
    "pid",
    "stray",
    "recordings/plans.json",
    "File name too long",
    "--config",
    "--config.sumo.workers=two",
    "--config.sampling.guidance.w_min=nan",
    "--workdir=",
    "empty/cache/metadata.json",
    "--config=configs/nosuch.py",
    "--baseline_dir=",
}


def _params():
  seen = set()
  for i, (script, _, named) in enumerate(CASES):
    marks = () if script not in seen or named in KINDS else (pytest.mark.slow,)
    seen.add(script)
    yield pytest.param(i, id=f"{script}-{i}", marks=marks)


@pytest.mark.parametrize("index", list(_params()))
def test_user_error_is_one_line_exit_2(inputs, index):
  script, args, named = CASES[index]
  new = inputs / "new" / str(index)
  argv = args.format(T=inputs, NEW=new).split()
  env = environ(JAX_PLATFORMS="cpu")
  proc = subprocess.run(
      [sys.executable, f"experiments/{script}.py", *argv],
      cwd=REPO,
      env=env,
      capture_output=True,
      text=True,
      timeout=120,
  )
  lines = [line for line in proc.stderr.splitlines() if not _INFO.match(line)]
  assert proc.returncode == 2, proc.stderr
  assert "Traceback" not in proc.stderr
  assert len(lines) == 1, proc.stderr
  assert lines[0].startswith(f"{script}: error: "), lines[0]
  assert named in lines[0]
  assert not new.exists()  # refused before anything was written


def test_cases_cover_every_script():
  scripts = {p.stem for p in (REPO / "experiments").glob("*.py")}
  assert {script for script, _, _ in CASES} == scripts


# In-process checks of the runner.


def _run(monkeypatch, main):
  monkeypatch.setattr("sys.argv", ["/x/evaluate.py"])
  with pytest.raises(SystemExit) as exit_info:
    cli.run(main)
  return exit_info.value.code


@pytest.mark.parametrize("error", [FileNotFoundError("no run"), PermissionError("denied")])
def test_path_errors_exit_2_with_the_message(monkeypatch, capsys, error):
  def main(argv):
    raise error

  assert _run(monkeypatch, main) == 2
  assert capsys.readouterr().err == f"evaluate: error: {error}\n"


def test_value_error_of_our_code_is_a_user_error(monkeypatch, capsys):
  def main(argv):
    diffusion_config.get_config("nosuch")

  assert _run(monkeypatch, main) == 2
  assert capsys.readouterr().err.startswith("evaluate: error: config arg 'nosuch'")


def test_a_user_error_raised_anywhere_is_one_line(monkeypatch, capsys):
  """What makes an error the user's is its class (errors.UserError), not where it was
  raised: here a test module, outside the package."""
  assert _run(monkeypatch, _raiser(DataError("/d/01_tracks.csv", "bad", row=3))) == 2
  assert capsys.readouterr().err == "evaluate: error: file /d/01_tracks.csv, row 3: bad\n"


def test_a_plain_value_error_of_our_code_keeps_its_traceback(monkeypatch, tmp_path):
  """A plain ValueError of the package is a bug (here a misuse of atomic.writing)."""

  def main(argv):
    with atomic.writing(tmp_path / "x", mode="a"):
      pass

  monkeypatch.setattr("sys.argv", ["prog"])
  with pytest.raises(ValueError, match="mode='a'") as info:
    cli.run(main)
  assert not isinstance(info.value, UserError)


@pytest.mark.parametrize("bug", [lambda: json.loads("{"), lambda: {}["key"]])
def test_other_errors_keep_their_traceback(monkeypatch, bug):
  """A ValueError raised inside a library (here json) is not the user's; nor a KeyError."""
  monkeypatch.setattr("sys.argv", ["prog"])
  with pytest.raises((ValueError, KeyError)):
    cli.run(lambda argv: bug())


def test_writable(tmp_path):
  (tmp_path / "file").write_text("x")
  assert cli.writable(tmp_path) and cli.writable(tmp_path / "a" / "b")
  assert not cli.writable(tmp_path / "file") and not cli.writable(tmp_path / "file" / "a")
  assert not (tmp_path / "a").exists()  # nothing made


def _raiser(error):
  def main(argv):
    raise error

  return main


_ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/run/metrics.json")
# what orbax re-raises from tensorstore when a checkpoint write finds the disk full
_TENSORSTORE_FULL = ValueError(
    'RESOURCE_EXHAUSTED: Failed writing: "/w/checkpoints/2.orbax-checkpoint-tmp/state/d/1a": '
    "Failed to write 1792272 bytes to file 8: No space left on device [os_error_code='28']"
)


@pytest.mark.parametrize(
    "error, named",
    [
        (_ENOSPC, "No space left on device: '/run/metrics.json'; free some space"),
        (OSError(errno.EDQUOT, os.strerror(errno.EDQUOT), "/q"), "free some space"),
        (OSError(errno.EROFS, os.strerror(errno.EROFS), "/ro/x"), "Read-only file system"),
        (
            OSError(errno.ENAMETOOLONG, os.strerror(errno.ENAMETOOLONG), "/" + "n" * 300),
            "File name too long",
        ),
        (_TENSORSTORE_FULL, "No space left on device [os_error_code='28']; free some space"),
    ],
)
def test_failures_of_the_machine_exit_2_with_one_line(monkeypatch, capsys, error, named):
  assert _run(monkeypatch, _raiser(error)) == 2
  err = capsys.readouterr().err
  assert err.startswith("evaluate: error: ") and err.count("\n") == 1 and named in err


@pytest.mark.parametrize(
    "error",
    [
        ValueError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 8 bytes"),
        RuntimeError("NOT_FOUND: no such key [os_error_code='2']"),  # ENOENT: not the machine
        OSError(errno.EIO, os.strerror(errno.EIO)),
    ],
)
def test_other_resource_and_os_errors_keep_their_traceback(monkeypatch, error):
  monkeypatch.setattr("sys.argv", ["prog"])
  with pytest.raises(type(error)):
    cli.run(_raiser(error))


def test_keyboard_interrupt_in_process_exits_130(monkeypatch, capsys):
  assert _run(monkeypatch, _raiser(KeyboardInterrupt())) == 130
  assert capsys.readouterr().err == "evaluate: error: interrupted; rerun to resume\n"


def _start_as_in_a_terminal(args: list[str]) -> subprocess.Popen:
  """`args` started in the repository on CPU, text pipes, SIGINT at its default as in a
  terminal: a parent that ignores it (an xdist worker may) would pass the ignore on to the
  child, which then never sees the signal."""
  return subprocess.Popen(
      args,
      cwd=REPO,
      env=environ(JAX_PLATFORMS="cpu"),
      stdout=subprocess.PIPE,
      stderr=subprocess.PIPE,
      text=True,
      preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
  )


def test_sigint_gives_one_line_and_status_130(tmp_path):
  script = tmp_path / "sleeper.py"
  script.write_text(
      "import sys, time\n"
      "from cvmdx_jax import cli\n"
      "def main(argv):\n"
      "  print('ready', flush=True)\n"
      "  time.sleep(60)\n"
      "cli.run(main)\n"
  )
  proc = _start_as_in_a_terminal([sys.executable, str(script)])
  try:
    assert proc.stdout.readline() == "ready\n"
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=30)
  finally:
    proc.kill()
  assert proc.returncode == 130, stderr
  assert stderr == "sleeper: error: interrupted; rerun to resume\n"


def test_every_script_handles_signals_before_its_imports():
  """cli's import installs the signal lines for the imports that follow it; run_exported.py
  imports nothing of cvmdx_jax and installs its own before it imports anything but the
  standard library."""
  import ast

  for path in sorted((REPO / "experiments").glob("*.py")):
    tree = ast.parse(path.read_text())
    imports = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    if path.stem == "run_exported":
      guard = next(n for n in tree.body if isinstance(n, ast.If))  # if __name__ == ...
      assert "signal.signal(signal.SIGINT, _stop)" in ast.unparse(guard)
      before = [
          n.names[0].name if isinstance(n, ast.Import) else n.module
          for n in imports
          if n.lineno < guard.lineno
      ]
      assert all(name in sys.stdlib_module_names for name in before), before
      after = [n.names[0].name for n in imports if n.lineno > guard.lineno]
      assert after == ["jax", "numpy"], after
      continue
    names = [a.name for a in imports[0].names]
    assert (getattr(imports[0], "module", None), names) == ("cvmdx_jax", ["cli"]), path.name


def test_run_exported_stops_with_one_line(tmp_path):
  """run_exported.py blocked reading its manifest (a FIFO) gets Ctrl-C: one line, 130."""
  (tmp_path / "export").mkdir()
  fifo = tmp_path / "export" / "manifest.json"
  os.mkfifo(fifo)
  proc = _start_as_in_a_terminal(
      [
          sys.executable,
          "experiments/run_exported.py",
          f"--export_dir={tmp_path / 'export'}",
          f"--inputs={tmp_path / 'in.npz'}",
          f"--out={tmp_path / 'out.npz'}",
      ]
  )
  try:
    with open(fifo, "w"):  # returns once the script opened it: it is past its imports
      proc.send_signal(signal.SIGINT)
      out, err = proc.communicate(timeout=60)
  finally:
    proc.kill()
  assert (proc.returncode, out, err) == (130, "", "run_exported: error: interrupted\n")
  assert not (tmp_path / "out.npz").exists()


def _imports_jaxlib(pid: int) -> bool:
  """Whether process `pid` has loaded jaxlib's extension (it is importing JAX)."""
  try:
    return "jaxlib" in Path(f"/proc/{pid}/maps").read_text()
  except OSError:
    return False


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize(
    "script, signum", [("evaluate", signal.SIGINT), ("train_diffusion", signal.SIGTERM)]
)
def test_a_signal_during_the_imports_gives_one_line(script, signum):
  """The signal arrives once JAX's extension is loaded: the script still has seconds of
  imports ahead (flax, orbax, its modules) before `cli.run` installs its handlers."""
  proc = _start_as_in_a_terminal([sys.executable, str(REPO / "experiments" / f"{script}.py")])
  try:
    while not _imports_jaxlib(proc.pid) and proc.poll() is None:
      time.sleep(0.01)
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)
  finally:
    proc.kill()
  what = "interrupted" if signum == signal.SIGINT else "terminated"
  assert (proc.returncode, out, err) == (
      128 + signum,
      "",
      f"{script}: error: {what}; rerun to resume\n",
  )
