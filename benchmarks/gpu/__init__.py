"""The GPU check: one command that builds the CUDA kernels, runs the CUDA tests, benchmarks the
operators, the forecasting step and a training burst, and writes everything to one folder.

``bash benchmarks/gpu/run.sh OUTDIR`` (see README.md in this folder); ``python -m
benchmarks.gpu.report OUTDIR`` turns the folder into markdown tables.
"""
