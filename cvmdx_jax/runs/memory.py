"""Resident memory of this process, and handing freed memory back between the demo's stages.

`peak_rss` is the process's high-water mark (`getrusage(RUSAGE_SELF).ru_maxrss`, never
lower than any earlier reading), `current_rss` the resident set now (`VmRSS` of
/proc/self/status; None off Linux). `release` drops what the process only keeps for reuse:
Python garbage, JAX's compiled executables and traces (`jax.clear_caches`), and the pages
the host allocator holds freed (`host_allocator`: jemalloc without decay, or glibc without
trimming, keep every freed page mapped until asked; `release_freed`: jemalloc's
`arena.<all>.purge`, or glibc's `malloc_trim(0)`). It changes no result, only what the
next call recompiles.
`call_peak` measures one call: the most resident memory above its start, from a thread
that reads `current_rss` every few milliseconds while the call runs.
"""

import ctypes
import gc
import resource
import sys
import threading
import time

import jax

_MALLCTL_ARENAS_ALL = 4096  # jemalloc's MALLCTL_ARENAS_ALL: "every arena" in a mallctl name


def peak_rss() -> int:
  """The process's peak resident memory so far, bytes (Linux reports KiB, macOS bytes)."""
  peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
  return peak if sys.platform == "darwin" else peak * 1024


def current_rss() -> int | None:
  """The process's resident memory now, bytes (`VmRSS`); None where /proc is missing."""
  try:
    with open("/proc/self/status", encoding="ascii") as f:
      for line in f:
        if line.startswith("VmRSS:"):
          return int(line.split()[1]) * 1024
  except OSError:
    return None
  return None


def release_freed() -> str:
  """Returns the host allocator's freed pages to the system; the allocator's name."""
  process = ctypes.CDLL(None)
  mallctl = getattr(process, "mallctl", None)
  if mallctl is not None:  # jemalloc (preloaded): purge every arena's dirty and muzzy pages
    name = f"arena.{_MALLCTL_ARENAS_ALL}.purge".encode()
    if mallctl(name, None, None, None, ctypes.c_size_t(0)) == 0:
      return "jemalloc"
  trim = getattr(process, "malloc_trim", None)
  if trim is not None:  # glibc
    trim(ctypes.c_size_t(0))
    return "glibc"
  return "none"


def release() -> str:
  """Frees what the process only keeps for reuse (module docstring); the allocator's name."""
  gc.collect()
  jax.clear_caches()
  gc.collect()
  return release_freed()


def rss_line() -> str:
  """'peak RSS <MiB> MiB, now <MiB> MiB' of this process (`peak_rss`, `current_rss`)."""
  now = current_rss()
  now_text = "?" if now is None else f"{now / 2**20:.0f}"
  return f"peak RSS {peak_rss() / 2**20:.0f} MiB, now {now_text} MiB"


def call_peak(fn, interval_s: float = 0.002):
  """(fn(), the most resident memory above the start while fn ran, bytes), sampled every
  `interval_s` s (a peak shorter than that can be missed; the host allocator decides
  whether freed pages leave the resident set: run with CVMDX_ALLOCATOR=system to see the
  live memory)."""
  start = current_rss() or 0
  peak = [start]
  done = threading.Event()

  def watch():
    while not done.is_set():
      peak[0] = max(peak[0], current_rss() or 0)
      time.sleep(interval_s)

  watcher = threading.Thread(target=watch, daemon=True)
  watcher.start()
  try:
    result = fn()
  finally:
    done.set()
    watcher.join()
  peak[0] = max(peak[0], current_rss() or 0)
  return result, peak[0] - start
