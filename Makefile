# Set-up and checks in one command each. `make test` is what CI runs (.ci/run).
PYTHON ?= python
PIP := $(PYTHON) -m pip

.PHONY: install demo test cuda-check bench lint

# Installs what is missing, then builds the kernels. torch is only installed when absent:
# 2.13.0 is the CPU build these machines carry on disk; a GPU machine keeps its CUDA torch.
install:
	$(PYTHON) -c "import torch" 2>/dev/null || $(PIP) install torch==2.13.0
	$(PIP) install numpy tqdm matplotlib pyyaml pybind11 ninja pytest pytest-benchmark ruff==0.17.6
	$(PIP) install --no-build-isolation -e .

# The main job: metrics table and pictures of the shipped world models on held-out synthetic scenes.
demo: install
	$(PYTHON) -m t3fast demo --out demo

# nvcc -c of every pure-CUDA kernel file (sm_80, sm_90); skipped where nvcc is absent.
cuda-check:
	bash .ci/cuda_compile_check.sh

lint:
	$(PYTHON) -m ruff check t3fast tests benchmarks setup.py

test: install cuda-check lint
	$(PYTHON) -m pytest -q

bench: install
	$(PYTHON) -m pytest benchmarks --benchmark-only --benchmark-json=benchmarks/results/cpu.json
