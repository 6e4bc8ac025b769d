# Two entry points (see README): `make serve` and `make test`. Both set up .venv from nothing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PORT ?= 8000
# Loopback only by default; `make serve HOST=0.0.0.0` serves the network (then set CRESTEREO_API_KEY).
HOST ?= 127.0.0.1

TORCH := torch==2.13.0
CPU_INDEX := https://download.pytorch.org/whl/cpu

# Serving needs the package and its runtime dependencies only; testing adds the `test` extra.
# torch first, as the CPU build: from PyTorch's CPU wheel index (`+cpu`), else, where that index
# cannot be reached, the plain pin (a package index may then resolve it to the CUDA build, several
# GB; on the project's build machines the plain pin is a CPU wheel on local disk).
$(VENV)/.serve-installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet --extra-index-url $(CPU_INDEX) '$(TORCH)+cpu' 2>/dev/null \
		|| $(PY) -m pip install --quiet '$(TORCH)'
	$(PY) -m pip install --quiet -e .
	touch $@

$(VENV)/.test-installed: $(VENV)/.serve-installed
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

.PHONY: setup setup-test serve lint test test-fast
setup: $(VENV)/.serve-installed
setup-test: $(VENV)/.test-installed

# First lite's OpenVINO graphs (`crestereo-pp prepare`: a minute or two the first time, then read
# from the cache), so that the service computes compiled from its first request; where they cannot
# be exported it computes on torch.
serve: setup
	-$(VENV)/bin/crestereo-pp prepare
	$(PY) -m crestereo_pp.service --host $(HOST) --port $(PORT)

# Style and types (configured in pyproject.toml): ruff's lint and format check on the whole tree,
# mypy on the packages. `make test` runs it first, so a lint or type error fails the tests (and CI).
lint: setup-test
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) tools/package_tree.py build/typecheck
	$(PY) -m mypy

test: lint
	$(PY) -m pytest -q

# The inner loop: everything but the tests that start servers, browsers, containers or other
# processes (marked `slow`, tests/conftest.py). `make test` runs them all, as CI does.
test-fast: setup-test
	$(PY) -m pytest -q -m "not slow"

# The prepared GPU check (bench/gpu_check/; README, "Development"): for a GPU machine with torch
# preinstalled and no package index, so it runs that machine's python3 from the tree, not the venv
# (its stages import the project through a link tree, tools/package_tree.py).
GPU_PYTHON ?= python3
GPU_OUT ?= $(or $(OUT),gpu-check)
.PHONY: gpu
gpu:
	$(GPU_PYTHON) bench/gpu_check --out $(GPU_OUT)
