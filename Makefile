# Set-up and checks in one command each. `make test` is what CI runs (.ci/run).
PYTHON ?= python
PIP := $(PYTHON) -m pip

.PHONY: install browser demo test cuda-check bench lint

# Installs what is missing, then builds the kernels. torch is only installed when absent:
# 2.13.0 is the CPU build these machines carry on disk; a GPU machine keeps its CUDA torch.
install:
	$(PYTHON) -c "import torch" 2>/dev/null || $(PIP) install torch==2.13.0
	$(PIP) install numpy tqdm matplotlib pyyaml pybind11 ninja pytest pytest-benchmark ruff==0.17.6
	$(PIP) install --no-build-isolation -e .

# Headless Chromium for the 3D viewer's browser tests (Debian package; they are skipped without it).
browser:
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null || \
	  apt-get install -y -qq --no-install-recommends chromium >/dev/null 2>&1 || \
	  (apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium) || \
	  echo "chromium could not be installed: the browser tests will be skipped"

# The main job: metrics, pictures and 3D pages of the shipped world models on held-out synthetic
# scenes; it ends by printing the path of demo/index.html.
demo: install
	$(PYTHON) -m t3fast demo --out demo

# nvcc -c of every pure-CUDA kernel file (sm_80, sm_90); skipped where nvcc is absent.
cuda-check:
	bash .ci/cuda_compile_check.sh

lint:
	$(PYTHON) -m ruff check t3fast tests benchmarks setup.py

test: install browser cuda-check lint
	$(PYTHON) -m pytest -q

bench: install
	$(PYTHON) -m pytest benchmarks --benchmark-only --benchmark-json=benchmarks/results/cpu.json
