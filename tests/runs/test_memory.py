"""cvmdx_jax.runs.memory: readings of this process's resident memory, and `release`."""

import ctypes
import gc
import time

import jax
import jax.numpy as jnp
import numpy as np

from cvmdx_jax.runs import memory


def test_peak_grows_with_touched_pages_and_stays():
  before = memory.peak_rss()
  block = np.ones(64 * 2**20 // 8)  # 64 MiB, every page touched
  during = memory.current_rss()
  after = memory.peak_rss()
  del block
  gc.collect()
  assert during >= 64 * 2**20
  assert after >= during - 2**20  # VmRSS and ru_maxrss: the same pages, read apart
  assert after >= before
  assert memory.peak_rss() >= after  # a high-water mark never falls


def test_current_rss_matches_proc_status_in_kib():
  with open("/proc/self/status", encoding="ascii") as f:
    kib = next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))
  now = memory.current_rss()
  assert now % 1024 == 0
  assert abs(now - kib * 1024) < 16 * 2**20  # the same reading, a few pages apart


def test_release_clears_compiled_functions_and_names_the_allocator():
  f = jax.jit(lambda x: x * 2.0)
  f(jnp.ones(3))
  assert f._cache_size() == 1
  allocator = memory.release()
  assert f._cache_size() == 0  # the next call compiles again
  has_mallctl = hasattr(ctypes.CDLL(None), "mallctl")
  assert allocator == ("jemalloc" if has_mallctl else "glibc")
  np.testing.assert_array_equal(f(jnp.ones(3)), np.full(3, 2.0))


def test_rss_line_reads_both_numbers():
  line = memory.rss_line()
  peak, now = (int(part.split()[-2]) for part in line.split(", "))
  assert line.startswith("peak RSS ") and peak >= now > 0


def test_call_peak_sees_a_block_freed_before_the_call_returns():
  def touch_and_free():
    block = np.ones(96 * 2**20 // 8)  # 96 MiB, freed when the function returns
    time.sleep(0.05)
    return float(block[0])

  value, peak = memory.call_peak(touch_and_free)
  assert value == 1.0
  assert 90 * 2**20 <= peak <= 160 * 2**20
  _, idle = memory.call_peak(lambda: time.sleep(0.05))
  assert idle < 16 * 2**20
