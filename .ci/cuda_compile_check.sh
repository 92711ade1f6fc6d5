#!/usr/bin/env bash
# Compile check of the CUDA sources, runnable without a GPU and without a CUDA build of torch:
#   * nvcc -c of every pure-CUDA kernel file csrc/cuda/*_kernel.cu for sm_80 and sm_90, with
#     the half/bfloat16 macros torch's CUDA extensions are built with;
#   * g++ -fsyntax-only of every torch glue file csrc/cuda/*.cpp against the installed torch's
#     headers, except stream.cpp (the one file that includes c10/cuda, whose headers only
#     compile in a CUDA build of torch), in the C++ standard torch builds extensions with.
# Skipped (exit 0) when nvcc is not installed; exits 1 on any compile error or warning.
set -euo pipefail

cd "$(dirname "$0")/.."

NVCC="$(command -v nvcc || true)"
if [[ -z "${NVCC}" ]]; then
  echo "cuda_compile_check: nvcc not found, CUDA compile check skipped"
  exit 0
fi

CUDA_INCLUDE="$(cd "$(dirname "${NVCC}")/.." && pwd)/include"
if [[ ! -f "${CUDA_INCLUDE}/cuda_runtime.h" ]]; then
  CUDA_INCLUDE=/usr/local/cuda/include
fi
PYTHON="${PYTHON:-python}"
TORCH_INCLUDES="$("${PYTHON}" -c \
  'from torch.utils.cpp_extension import include_paths; print(" ".join(include_paths()))')"
PY_INCLUDE="$("${PYTHON}" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"

BUILD="$(mktemp -d)"
trap 'rm -rf "${BUILD}"' EXIT

# Each check runs as a background job, at most one per core, into its own log; the results are
# reported in source order once all have finished.
JOBS="$(nproc)"
checks=()
check() {  # check <what> <command...>: queues it; it fails on errors and on any compiler output
  local what="$1"
  shift
  local log="${BUILD}/${#checks[@]}.log"
  checks+=("${what}")
  while (( $(jobs -rp | wc -l) >= JOBS )); do wait -n || true; done
  ( if "$@" >"${log}" 2>&1 && [[ ! -s "${log}" ]]; then touch "${log}.ok"; fi ) &
}
report() {  # report <heading>: waits for every queued check and prints them under the heading
  wait
  echo "$1"
  local i
  for i in "${!checks[@]}"; do
    if [[ -e "${BUILD}/${i}.log.ok" ]]; then
      echo "  ok    ${checks[$i]}"
    else
      echo "  FAIL  ${checks[$i]}"
      cat "${BUILD}/${i}.log"
      status=1
    fi
  done
}
status=0

echo "cuda_compile_check: $("${NVCC}" --version | grep -o "release [0-9.]*")"
shopt -s nullglob
for src in csrc/cuda/*_kernel.cu; do
  check "${src}" "${NVCC}" -c "${src}" -o "${BUILD}/$(basename "${src}" .cu).o" \
    -std=c++17 -O3 --expt-relaxed-constexpr -Icsrc \
    -gencode arch=compute_80,code=sm_80 -gencode arch=compute_90,code=sm_90 \
    -D__CUDA_NO_HALF_OPERATORS__ -D__CUDA_NO_HALF_CONVERSIONS__ \
    -D__CUDA_NO_BFLOAT16_CONVERSIONS__ -D__CUDA_NO_HALF2_OPERATORS__ \
    -Werror all-warnings
done

TORCH_VERSION="$("${PYTHON}" -c 'import torch; print(torch.__version__)')"
TORCH_FLAGS=()
for dir in ${TORCH_INCLUDES}; do TORCH_FLAGS+=(-isystem "${dir}"); done
skipped=()
for src in csrc/cuda/*.cpp; do
  if [[ "$(basename "${src}")" == "stream.cpp" ]]; then
    skipped+=("${src}")
    continue
  fi
  check "${src}" g++ -std=c++20 -fsyntax-only -Wall -Wextra -Werror \
    "${TORCH_FLAGS[@]}" -isystem "${CUDA_INCLUDE}" -isystem "${PY_INCLUDE}" -Icsrc \
    -DTORCH_EXTENSION_NAME=_C "${src}"
done
report "kernels (nvcc -c, sm_80 + sm_90) and glue (g++ -fsyntax-only against torch ${TORCH_VERSION}):"
for src in "${skipped[@]}"; do
  echo "  skip  ${src} (includes c10/cuda; compiled only in a CUDA build of torch)"
done

if [[ ${status} -ne 0 ]]; then
  echo "cuda_compile_check: FAILED"
  exit 1
fi
echo "cuda_compile_check: passed"
