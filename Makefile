# Every target builds .venv from nothing when it is missing or stale.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo test test-slow benchmark clean

# The pinned dependencies, then this project editable (cvmdx_jax and configs importable from
# anywhere; edits take effect without reinstalling). setuptools >= 70.1 builds it without
# the wheel package; --no-deps: the lock already holds every dependency.
$(STAMP): requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip "setuptools>=70.1"
	$(PY) -m pip install -q -r requirements.lock
	$(PY) -m pip install -q --no-deps --no-build-isolation -e .
	touch $(STAMP)

install: $(STAMP)

## The main job: SUMO data -> CVQ-VAE -> diffusion -> evaluation (runs/demo/).
demo: $(STAMP)
	$(PY) experiments/run_demo.py --workdir=runs/demo

## The default test run (~15 min on 2 cores).
test: $(STAMP)
	$(PY) -m pytest -q -n 2 -m "not slow"

## Long tests (kill-and-resume, bigger configs).
test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

benchmark: $(STAMP)
	$(PY) experiments/benchmark_sampling.py
	$(PY) experiments/benchmark.py
	@echo "side by side with the official code: ../shared/reference_bench/README.md, then"
	@echo "  $(PY) experiments/benchmark.py --reference_json=ours.json --official_json=official.json"

clean:
	rm -rf $(VENV) runs
