# Two entry points (see README): `make serve` and `make test`. Both set up .venv from nothing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PORT ?= 8000
# Loopback only by default; `make serve HOST=0.0.0.0` serves the network (then set CRESTEREO_API_KEY).
HOST ?= 127.0.0.1

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# The CPU build of torch (an unpinned torch would pull a multi-GB CUDA build).
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

.PHONY: setup serve lint test
setup: $(VENV)/.installed

serve: setup
	$(PY) -m service --host $(HOST) --port $(PORT)

# Style and types (configured in pyproject.toml): ruff's lint and format check on the whole tree,
# mypy on the packages. `make test` runs it first, so a lint or type error fails the tests (and CI).
lint: setup
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy

test: lint
	$(PY) -m pytest -q

# The prepared GPU check (bench/gpu_check.py; README, "Development"): for a GPU machine with torch
# preinstalled and no package index, so it runs that machine's python3 from the tree, not the venv.
GPU_PYTHON ?= python3
GPU_OUT ?= $(or $(OUT),gpu-check)
.PHONY: gpu
gpu:
	PYTHONPATH=. $(GPU_PYTHON) bench/gpu_check.py --out $(GPU_OUT)
