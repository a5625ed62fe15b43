# Two entry points: `make run` (set up, then the main job) and `make test` (set up, then the suite).
VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
OUT ?= out

.PHONY: run test install dev lint bench clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

# pyproject pins torch==2.13.0, which pip takes from the local CPU wheel (never a CUDA build).
$(VENV)/.installed: pyproject.toml | $(PY)
	$(PY) -m pip install -q -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml | $(PY)
	$(PY) -m pip install -q -e ".[dev]"
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
dev: $(VENV)/.installed-dev

run: $(VENV)/.installed
	$(VENV)/bin/telesplat body demo --out $(OUT)/body_demo.mp4

test: $(VENV)/.installed-dev
	$(PY) -m ruff check .
	# Two workers on two cores: one thread each, or the torch / numba pools oversubscribe.
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(PY) -m pytest -q -n 2

lint: $(VENV)/.installed-dev
	$(PY) -m ruff check .

bench: $(VENV)/.installed-dev
	$(PY) bench/body.py

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
