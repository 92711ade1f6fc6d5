#!/usr/bin/env bash
# The test suite under another torch release and Python, with the CUDA kernels built where nvcc
# is found (no GPU needed: the CUDA tests skip). For example the GPU machines' versions:
#   bash .ci/other_torch.sh python3.12 2.11.0            # then any pytest arguments
#   bash .ci/other_torch.sh python3.12 2.11.0 tests/ops -x
# It makes (or reuses) a virtual environment ${VENV_ROOT:-/tmp}/t3fast-torch<version>-<python>,
# installs that torch from PyPI (the CUDA build with CUDA's wheels: about 3 GB), clones the
# repository's HEAD into it, runs `make install` there (the other dependencies, and the kernels
# built for sm_90 as the GPU check builds them) and then pytest. Not part of CI: the download.
set -euo pipefail

if [[ $# -lt 2 ]]; then
  echo "usage: bash .ci/other_torch.sh PYTHON TORCH_VERSION [pytest arguments...]" >&2
  exit 2
fi
PYTHON_EXE="$1"
TORCH_VERSION="$2"
shift 2
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
VENV="${VENV_ROOT:-/tmp}/t3fast-torch${TORCH_VERSION}-$(basename "${PYTHON_EXE}")"

if [[ ! -x "${VENV}/bin/python" ]]; then
  "${PYTHON_EXE}" -m venv "${VENV}"
fi
"${VENV}/bin/pip" install -q "torch==${TORCH_VERSION}" setuptools

# torch finds the toolkit from nvcc's folder, which a wrapper script elsewhere hides
if [[ -z "${CUDA_HOME:-}" ]]; then
  for candidate in /usr/local/cuda /usr/local/cuda-*; do
    if [[ -f "${candidate}/include/cuda_runtime.h" ]]; then
      export CUDA_HOME="${candidate}"
      break
    fi
  done
fi
BUILD_ENV=(T3FAST_NO_CUDA=1)
if command -v nvcc >/dev/null && [[ -n "${CUDA_HOME:-}" ]]; then
  BUILD_ENV=(FORCE_CUDA=1 TORCH_CUDA_ARCH_LIST=9.0)
fi

CLONE="${VENV}/t3fast"
rm -rf "${CLONE}"
git clone -q "${ROOT}" "${CLONE}"
cd "${CLONE}"
env "${BUILD_ENV[@]}" MAX_JOBS="$(nproc)" make install PYTHON="${VENV}/bin/python" >install.log 2>&1 || {
  tail -30 install.log
  exit 1
}
"${VENV}/bin/python" -c 'import t3fast; print("t3fast", t3fast.build_info())'
exec "${VENV}/bin/python" -m pytest -q -p no:cacheprovider "$@"
