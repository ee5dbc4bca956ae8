# `make test` and `make demo` do all set-up on a fresh machine; a second run reuses it.
# VENV=/path/to/env reuses an existing environment (e.g. one with a CUDA torch).
VENV      ?= .venv
PY        := $(VENV)/bin/python
PIP       := $(PY) -m pip
TORCH_PIN ?= torch==2.13.0
DEPS      := scikit-build-core pybind11 ninja cmake numpy tqdm pillow matplotlib scipy \
             pytest pytest-timeout hypothesis nbclient nbformat ipykernel transformers safetensors \
             opencv-python-headless diffusers==0.42.* viser==1.1.1 selenium
CSRC      := $(shell find csrc -type f 2>/dev/null) CMakeLists.txt pyproject.toml
BUILT     := $(VENV)/.tiger-built
PYTEST_ARGS ?=

.PHONY: test demo env build cuda-check bench clean

env: $(VENV)/.tiger-env
$(VENV)/.tiger-env: pyproject.toml tools/ensure_eigen.sh tools/ensure_browser.sh
	@test -x $(PY) || python3 -m venv $(VENV)
	@# torch only when it is missing: a user's own (CUDA) torch is kept.
	@$(PY) -c "import torch" 2>/dev/null || $(PIP) install -q $(TORCH_PIN)
	$(PIP) install -q $(DEPS)
	bash tools/ensure_eigen.sh
	bash tools/ensure_browser.sh
	@touch $@

build: $(BUILT)
$(BUILT): $(VENV)/.tiger-env $(CSRC)
	$(PIP) install -q --no-build-isolation --no-deps -e .
	@touch $@

# CI has no GPU: compile every .cu with this machine's nvcc so CUDA errors fail CI.
cuda-check: $(VENV)/.tiger-env
	bash tools/check_cuda_compile.sh
	PY=$(PY) bash tools/check_cuda_glue.sh

test: build cuda-check
	$(PY) -m pytest -q $(PYTEST_ARGS)

demo: build
	$(PY) -m tiger.cli.main demo --out outputs/demo --force

bench: build
	$(PY) -m benchmarks.rasterize

clean:
	rm -rf build $(BUILT)
