# Two entry points (see README): `make serve` and `make test`. Both set up .venv from nothing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PORT ?= 8000

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# The CPU build of torch (an unpinned torch would pull a multi-GB CUDA build).
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

.PHONY: setup serve test
setup: $(VENV)/.installed

serve: setup
	$(VENV)/bin/uvicorn service.app:create_app --factory --host 0.0.0.0 --port $(PORT)

test: setup
	$(PY) -m pytest -q
