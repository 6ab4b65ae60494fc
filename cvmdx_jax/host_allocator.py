"""The host memory allocator of the entry points: keep freed memory instead of returning it.

XLA:CPU allocates each execution's large buffers anew. With glibc's defaults every buffer
above 32 MB is a fresh `mmap` that is page-faulted in on first touch and unmapped when
freed, so each training step pays for ~0.9 M page faults (reference-size U-Net, batch 256:
~2.4 s of system time per step on 2 cores; docs/log, "Host allocator"). An allocator
that keeps freed pages mapped removes that. The training entry points
(`cli.run(main, allocator=True)`) re-execute themselves once, before any work, with
- jemalloc preloaded without page decay (`MALLOC_CONF=dirty_decay_ms:-1,muzzy_decay_ms:-1`)
  where `libjemalloc.so.2` is installed (Debian / Ubuntu: `apt-get install libjemalloc2`),
  or the path in `CVMDX_JEMALLOC`;
- otherwise glibc's own allocator told not to use `mmap` or trim, and to back its heap with
  transparent huge pages (`GLIBC_TUNABLES`; `hugetlb` needs glibc >= 2.35, older ones
  ignore it). One arena (`arena_max=1`), the setting until 2026-12-03, made the B = 1
  prediction ~15 % slower and the training step no faster on 2 cores (BUILD_NOTES.md).
Only on Linux. The choice is the option `CVMDX_ALLOCATOR`:
- `auto` (or unset): the above, except where `JAX_PLATFORMS` names an accelerator first
  (`cuda`, `gpu`, `rocm`, `tpu`, ...): there the large buffers live in device memory, and
  the process is left as started (XLA's plain setting, as for the other performance
  options, `models.performance`). Without `JAX_PLATFORMS` a GPU host is not detected (that
  would need JAX imported) and gets the re-execution: harmless, ~1.6 s of start-up;
- `jemalloc`: jemalloc or an error where it is not found; `glibc`: the tunables even
  where jemalloc is installed;
- `system`: the process as started (the tests set it).
Any other value is a `ValueError` naming the variable (`cli.run`: one line, exit 2).
The price: the process keeps its peak memory until it exits (the peak itself is unchanged),
and the re-execution imports the script's modules twice (~1.6 s of start-up), which is why
only the trainers pay it, and not for `--help` (`HELP_FLAGS`).
"""

import os
import sys
from collections.abc import Mapping

from cvmdx_jax.errors import UserError

OPT_OUT = "CVMDX_ALLOCATOR"  # the option; "system": leave the allocator alone
CHOICES = ("auto", "jemalloc", "glibc", "system")
APPLIED = "CVMDX_ALLOCATOR_APPLIED"  # set in the re-executed process
JEMALLOC_ENV = "CVMDX_JEMALLOC"  # path of libjemalloc.so.2, overrides the search
JEMALLOC_PATHS = (
    "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2",
    "/usr/lib/aarch64-linux-gnu/libjemalloc.so.2",
    "/usr/lib64/libjemalloc.so.2",
    "/usr/lib/libjemalloc.so.2",
    "/usr/local/lib/libjemalloc.so.2",
)
JEMALLOC_CONF = "dirty_decay_ms:-1,muzzy_decay_ms:-1"
GLIBC_TUNABLES = (
    "glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=68719476736:" "glibc.malloc.hugetlb=1"
)
HELP_FLAGS = ("?", "help", "helpshort", "helpfull", "helpxml")  # absl's, after - or --


def _joined(environ: Mapping[str, str], name: str, value: str, sep: str) -> str:
  old = environ.get(name, "")
  return f"{value}{sep}{old}" if old else value


def accelerator_requested(environ: Mapping[str, str]) -> bool:
  """Whether `JAX_PLATFORMS` in `environ` names a platform other than "cpu" first (JAX's
  default backend is the first it lists)."""
  platforms = [p.strip() for p in environ.get("JAX_PLATFORMS", "").split(",") if p.strip()]
  return bool(platforms) and platforms[0] != "cpu"


def allocator_environment(
    environ: Mapping[str, str], platform: str = sys.platform, exists=os.path.isfile
) -> dict[str, str] | None:
  """The environment to re-execute with, or None to keep this process as it is.

  Args:
    environ: the current environment.
    platform: `sys.platform`.
    exists: path -> bool (for tests).

  Returns:
    A copy of `environ` with the allocator settings of the module docstring and `APPLIED`
    set; None on other platforms, after `CVMDX_ALLOCATOR=system`, for `auto` where
    `accelerator_requested`, or when already applied.

  Raises:
    ValueError: `CVMDX_ALLOCATOR` is not one of `CHOICES` or empty, `CVMDX_JEMALLOC`
      names a file that does not exist, or `jemalloc` is asked for and not found.
  """
  choice = environ.get(OPT_OUT, "") or "auto"
  if choice not in CHOICES:
    raise UserError(f"{OPT_OUT}={choice!r}: expected one of {', '.join(CHOICES)}")
  if (
      choice == "system"
      or environ.get(APPLIED)
      or not platform.startswith("linux")
      or (choice == "auto" and accelerator_requested(environ))
  ):
    return None
  env = dict(environ, **{APPLIED: "1"})
  jemalloc = None if choice == "glibc" else _find_jemalloc(environ, exists)
  if jemalloc:
    env["LD_PRELOAD"] = _joined(environ, "LD_PRELOAD", jemalloc, ":")
    env["MALLOC_CONF"] = _joined(environ, "MALLOC_CONF", JEMALLOC_CONF, ",")
  elif choice == "jemalloc":
    raise UserError(
        f"{OPT_OUT}=jemalloc: libjemalloc.so.2 is not in {', '.join(JEMALLOC_PATHS)}"
        f" (install libjemalloc2, or name it in {JEMALLOC_ENV})"
    )
  else:
    env["GLIBC_TUNABLES"] = _joined(environ, "GLIBC_TUNABLES", GLIBC_TUNABLES, ":")
  return env


def _find_jemalloc(environ: Mapping[str, str], exists) -> str | None:
  """`CVMDX_JEMALLOC` (checked) or the first of `JEMALLOC_PATHS` that exists, else None."""
  given = environ.get(JEMALLOC_ENV)
  if given and not exists(given):
    raise UserError(f"{JEMALLOC_ENV}={given}: no such file")
  return given or next((p for p in JEMALLOC_PATHS if exists(p)), None)


def in_force(environ: Mapping[str, str]) -> str:
  """What this process runs with: "jemalloc", "glibc tunables" or "system" (for reports)."""
  if not environ.get(APPLIED):
    return "system"
  return "jemalloc" if "libjemalloc" in environ.get("LD_PRELOAD", "") else "glibc tunables"


def reexec_with_allocator() -> None:
  """Re-executes this process (same interpreter and arguments) with
  `allocator_environment(os.environ)`, when that is not None and no help flag was given
  (absl prints the usage and exits: nothing to speed up); else returns."""
  if any(
      arg.startswith("-") and arg.lstrip("-").split("=", 1)[0] in HELP_FLAGS for arg in sys.argv[1:]
  ):
    return
  env = allocator_environment(os.environ)
  if env is not None:
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)
