#!/usr/bin/env bash
# The GPU check in one command (at most 10 minutes on one H100 / H200):
#   bash benchmarks/gpu/run.sh OUTDIR                   # build, CUDA tests, benchmarks, training burst
#   bash benchmarks/gpu/run.sh OUTDIR --device cpu --quick   # dry run of the script on a CPU
# Every stage runs even if an earlier one failed; OUTDIR/summary.md says which passed.
# Options: python -m benchmarks.gpu.run --help. Tables: python -m benchmarks.gpu.report OUTDIR
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "${ROOT}"
export PYTHONPATH="${ROOT}${PYTHONPATH:+:${PYTHONPATH}}"
exec "${PYTHON:-python}" benchmarks/gpu/run.py "$@"
