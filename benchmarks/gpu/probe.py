"""What the machine and the build are: ``python -m benchmarks.gpu.probe env|build --out FILE``.

``env``: Python, torch, CUDA, cuDNN and NCCL versions, the GPUs torch sees, nvcc and ninja.
``build``: ``t3fast.build_info()`` plus where ``t3fast`` was imported from and whether a bad call
raises its error (checked in a child process: a C++ runtime that does not match the compiler
can crash while the error message is formatted); with ``--expect-cuda`` it exits 1 unless the
kernels were built with CUDA, a GPU is visible and errors raise.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path


def _command_output(argv: list[str]) -> str | None:
    if shutil.which(argv[0]) is None:
        return None
    try:
        out = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"error: {exc}"
    return (out.stdout + out.stderr).strip()


def nccl_version() -> str:
    """``major.minor.patch`` (torch returns a tuple, or an int such as 2708 in old releases)."""
    import torch

    version = torch.cuda.nccl.version()
    return ".".join(map(str, version)) if isinstance(version, tuple) else str(version)


def environment() -> dict:
    import torch

    info = {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "cuda_available": torch.cuda.is_available(),
        "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
        "nvcc": _command_output(["nvcc", "--version"]),
        "ninja": _command_output(["ninja", "--version"]),
        "gpus": [],
    }
    if torch.cuda.is_available():
        try:
            info["nccl"] = nccl_version()
        except Exception as exc:  # NCCL may be absent from a build
            info["nccl"] = f"unavailable ({exc})"
        for index in range(torch.cuda.device_count()):
            props = torch.cuda.get_device_properties(index)
            info["gpus"].append({
                "name": props.name,
                "capability": f"{props.major}.{props.minor}",
                "memory_gb": round(props.total_memory / 1e9, 1),
                "multiprocessors": props.multi_processor_count,
            })
    return info


# A call the kernels refuse with a message that formats integers (argmax needs 1 to 256 classes).
_BAD_CALL = """
import torch
from t3fast.ops import triplane_decode
planes = [torch.zeros(1, 4, 3, 3), torch.zeros(1, 4, 3, 2), torch.zeros(1, 4, 3, 2)]
try:
    triplane_decode(*planes, [torch.zeros(300, 4)], [torch.zeros(300)], grid=(2, 2, 2), pe_freqs=0, argmax=True)
except RuntimeError as exc:
    print(exc)
"""


def error_check() -> tuple[bool, str]:
    """Whether a refused call raises its RuntimeError (run in a child: a crash must not end us)."""
    try:
        out = subprocess.run([sys.executable, "-c", _BAD_CALL], capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired:
        return False, "the refused call did not return in 120 s"
    message = out.stdout.strip()
    if out.returncode == 0 and "got 300" in message:
        return True, message
    return False, f"exit status {out.returncode}: {(message + ' ' + out.stderr.strip())[-300:]}"


def build() -> dict:
    import torch

    import t3fast

    info = dict(t3fast.build_info())
    info["imported_from"] = str(Path(t3fast.__file__).resolve().parent)
    info["gpu_visible"] = torch.cuda.is_available()
    info["errors_raise"], info["error_check"] = error_check()
    return info


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.gpu.probe", description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["env", "build"])
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--expect-cuda", action="store_true", help="fail unless CUDA kernels and a GPU are there")
    args = parser.parse_args(argv)
    info = environment() if args.what == "env" else build()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(info, indent=2) + "\n")
    print(json.dumps(info, indent=2))
    if args.expect_cuda:
        ok = info.get("cuda") if args.what == "build" else info.get("cuda_available")
        if not ok or not info.get("gpu_visible", info.get("cuda_available")):
            print("expected CUDA kernels and a visible GPU", file=sys.stderr)
            return 1
        if args.what == "build" and not info["errors_raise"]:
            print(f"a refused call crashed instead of raising: {info['error_check']}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
