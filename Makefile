# Every target builds .venv from nothing when it is missing or stale.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install jemalloc openmpi demo test test-slow benchmark benchmark-quality lint clean

# The pinned dependencies, then this project editable (cvmdx_jax and configs importable from
# anywhere; edits take effect without reinstalling); --no-deps: the lock already holds every
# dependency. Both go in with uv (12 s against pip's 52 s on 2 cores, BUILD_NOTES.md); where
# uv fails (e.g. an index that only pip's own configuration names), by pip, with setuptools
# >= 70.1 first (it builds the editable install without the wheel package).
UV_VERSION := 0.13.9
$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	($(PY) -m pip install -q uv==$(UV_VERSION) \
	  && $(VENV)/bin/uv pip install -q --python $(PY) -r requirements.lock \
	  && $(VENV)/bin/uv pip install -q --python $(PY) --no-deps -e .) \
	|| ($(PY) -m pip install -q --upgrade pip "setuptools>=70.1" \
	  && $(PY) -m pip install -q -r requirements.lock \
	  && $(PY) -m pip install -q --no-deps --no-build-isolation -e .)
	@$(MAKE) --no-print-directory jemalloc
	touch $(STAMP)

install: $(STAMP)

# jemalloc, the faster host allocator of the training scripts (docs/usage.md, "Host
# allocator"; training step ~7-13 % faster than with the glibc tunables): best effort, once,
# where it is missing and apt-get can install it without asking (root). JEMALLOC=0 skips it.
JEMALLOC ?= 1
jemalloc:
	@if [ "$(JEMALLOC)" = 1 ] && ! ldconfig -p 2>/dev/null | grep -q libjemalloc.so.2 \
	    && [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing libjemalloc2 with apt-get (faster training; JEMALLOC=0 skips it)"; \
	  DEBIAN_FRONTEND=noninteractive timeout 120 apt-get install -y -q libjemalloc2 \
	    >/dev/null 2>&1 || echo "libjemalloc2 not installed: the glibc tunables are used"; \
	fi

## The main job: SUMO data -> CVQ-VAE -> diffusion -> evaluation (runs/demo/).
demo: $(STAMP)
	$(PY) experiments/run_demo.py --workdir=runs/demo

## The default test run (6-10 min on 2 cores, install included).
test: $(STAMP)
	CVMDX_REQUIRE_SUMO=1 $(PY) -m pytest -q -n 2 -m "not slow"

## Long tests (kill-and-resume, bigger configs, launches under mpirun).
test-slow: $(STAMP)
	@$(MAKE) --no-print-directory openmpi
	CVMDX_REQUIRE_SUMO=1 $(PY) -m pytest -q -m slow

# Open MPI's mpirun for the slow test of a launch by a cluster's own launcher (docs/usage.md,
# "Several processes"): best effort, where missing and apt-get can install it (root).
openmpi:
	@if ! command -v mpirun >/dev/null 2>&1 && [ "$$(id -u)" = 0 ] \
	    && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing openmpi-bin with apt-get (the mpirun launch test)"; \
	  DEBIAN_FRONTEND=noninteractive timeout 300 apt-get install -y -q openmpi-bin \
	    >/dev/null 2>&1 || echo "openmpi-bin not installed: the mpirun test is skipped"; \
	fi

benchmark: $(STAMP)
	$(PY) experiments/benchmark_sampling.py
	$(PY) experiments/benchmark.py
	$(PY) experiments/benchmark_costs.py --workdir=runs/benchmark_costs
	@echo "side by side with the official code: ../shared/reference_bench/README.md, then"
	@echo "  $(PY) experiments/benchmark.py --reference_json=ours.json --official_json=official.json"

## The demo's trained models on large new SUMO test sets (>= 1,000 scenarios per class on the
## test roads and on the held-out road): proper scores, vehicle-bootstrap intervals, conformal
## regions -> runs/quality/quality.md (docs/results.md, "Quality benchmark"). Needs make demo;
## 19 min on 2 cores with the 2-step student (Intel Xeon, fresh clone, install included).
benchmark-quality: $(STAMP)
	$(PY) experiments/benchmark_quality.py --workdir=runs/quality --runs=runs/demo \
	  --max_scenarios=3000

## Linter and formatter in check mode (pyproject.toml's [tool.ruff], [tool.pyink]); nothing
## is rewritten. To apply both: `.venv/bin/ruff check --fix . && .venv/bin/pyink .`
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/pyink --check .

clean:
	rm -rf $(VENV) runs
