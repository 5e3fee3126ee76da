# Two entry points: `make demo` (set up + main job) and `make test` (set up + whole test suite).
# Set-up installs the local CPU torch wheel *before* the package, so pip never pulls a multi-GB
# CUDA build. GPU users: create .venv and install their own torch build first; an importable
# torch in .venv is kept as it is.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
TORCH_SPEC ?= torch==2.13.0
# glibc's allocator dominates torch on this kind of VM; these cut training steps ~2x
# (the values of racklay.runtime.MALLOC_ENV, which the benchmarks and tests use).
export MALLOC_MMAP_THRESHOLD_ ?= 4294967296
export MALLOC_TRIM_THRESHOLD_ ?= 4294967296
export GRADIO_ANALYTICS_ENABLED := False

.PHONY: setup demo test browser clean-venv
setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e '.[dev]'
	touch $@

# Debian's Chromium for the browser end-to-end tests (Playwright's own download fails offline).
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; \
	  else echo "chromium missing: sudo apt-get install -y chromium (browser tests will be skipped)"; fi; }

demo: setup
	$(VENV)/bin/transfer demo --real-photos datasets/real-photos

test: setup browser
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q

clean-venv:
	rm -rf $(VENV)
