"""t3fast's CUDA operators run on the CPU by an emulator, for testing them without a GPU.

The CUDA glue (``csrc/cuda/*.cpp``) and kernel files (``csrc/cuda/*_kernel.cu``) are compiled
by the host compiler against the headers in ``include/``, which stand in for the CUDA runtime,
``cuda_fp16.h``, ``cuda_bf16.h``, the pipeline primitives (``cuda_pipeline.h``) and WMMA
(``mma.h``): a block's threads run as fibers with real barriers and warp exchanges, shared
memory is per block with guard bytes, an asynchronous copy lands when its thread waits for it,
WMMA products round as the tensor cores do, and misuse (divergent barriers, misaligned fragment loads, overrunning
shared memory, a launch asking for more shared memory than it opted into) fails the launch
with a message; a misaligned vector load (e.g. a ``float4`` off its 16 bytes, which faults on
a GPU) aborts the process with UBSan's report. The glue registers its kernels as the CPU
kernels of a library ``t3fast_emu`` with t3fast's schemas, so ``torch.ops.t3fast_emu.<op>`` on
CPU tensors runs exactly what ``torch.ops.t3fast.<op>`` runs on a GPU: the glue's checks,
allocations and precision rules (it reads CUDA's autocast state and ``allow_tf32`` as on a
GPU), then the kernels. The only rewriting is mechanical: ``kernel<<<grid, block, smem, stream>>>(args)``
becomes a call, the dynamic ``extern __shared__`` buffer a pointer, and the glue's
``TORCH_LIBRARY_IMPL(t3fast, CUDA, m)`` registers for ``t3fast_emu`` on the CPU. What it
cannot show: speed, the hardware's memory model beyond barriers and atomics (blocks run one
at a time, in order), and cuBLAS (the glue's GEMMs run as CPU GEMMs).
"""

from __future__ import annotations

import hashlib
import platform
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

import pytest
import torch

#: the tests that build the emulator skip without a host C++ compiler, or off x86-64 (the
#: fibers switch stacks in x86-64 assembly)
requires_emulator = pytest.mark.skipif(
    (shutil.which("c++") is None and shutil.which("g++") is None) or platform.machine() not in ("x86_64", "AMD64"),
    reason="needs a host C++ compiler on x86-64")

HERE = Path(__file__).resolve().parent
CSRC = HERE.parents[1] / "csrc"

_SHARED = re.compile(r"extern\s+__shared__\s+__align__\(\d+\)\s+unsigned char\s+(\w+)\[\];")
_LAUNCH = re.compile(r"([A-Za-z_][\w:]*(?:<[^;{}<>]*>)?)<<<(.*?)>>>", re.DOTALL)
_KERNEL_PRELUDE = "#define __CUDACC__ 1\n#define __CUDA_ARCH__ 900\n#include <t3emu_device.h>\n"
_MM_TO = re.compile(r"at::mm\(([^,()]+(?:\(\))?), ([^,()]+(?:\[\w+\])?), (\w+)\)")
_SCHEMAS = re.compile(r"^TORCH_LIBRARY\(t3fast, m\) \{\n.*?^\}\n", re.DOTALL | re.MULTILINE)


def rewrite_kernels(source: str) -> str:
    """A kernel file as host C++ for the emulator (see the module docstring)."""
    source = _SHARED.sub(r"unsigned char* \1 = ::t3emu::dynamic_smem();", source)
    source = _LAUNCH.sub(r"::t3emu::launch(\1, \2)", source)
    return _KERNEL_PRELUDE + source


def _replace_required(source: str, old: str, new: str, what: str) -> str:
    """``source`` with ``old`` replaced by ``new``; an error naming ``what`` when the source no
    longer holds ``old`` (the rewrite would silently do nothing)."""
    if old not in source:
        raise ValueError(f"{what} no longer holds {old.strip()!r}: the emulator's rewrite needs updating")
    return source.replace(old, new)


def rewrite_glue(source: str) -> str:
    """A glue file registering its kernels for ``t3fast_emu`` on the CPU. Its GEMMs with a
    float32 result of low-precision operands (``at::mm(a, b, acc)``, CUDA only) become float32
    GEMMs of the same operands: exact products accumulated in float32, as cuBLAS computes them."""
    source = _MM_TO.sub(r"at::mm((\1).to(\3), (\2).to(\3))", source)
    return _replace_required(source, "TORCH_LIBRARY_IMPL(t3fast, CUDA, m)", "TORCH_LIBRARY_IMPL(t3fast_emu, CPU, m)",
                             "a CUDA glue file")


def rewrite_checks(source: str) -> str:
    """``csrc/checks.h`` with every tensor taken for a CUDA tensor where the dtypes a backend
    accepts are checked: the emulated glue's tensors live on the CPU."""
    return _replace_required(source, "  if (t.is_cuda()) {", "  if (true) {  // emulated CUDA", "csrc/checks.h")


def schemas(source: str) -> str:
    """t3fast's operator schemas (from ``csrc/t3fast.cpp``) as the library ``t3fast_emu``."""
    block = _SCHEMAS.search(source)
    if block is None:
        raise ValueError("csrc/t3fast.cpp has no TORCH_LIBRARY(t3fast, m) block")
    return "#include <torch/library.h>\n\n" + block.group(0).replace("TORCH_LIBRARY(t3fast, m)",
                                                                     "TORCH_LIBRARY(t3fast_emu, m)")


def _generated() -> dict[str, str]:
    # the glue and triplane_args.cpp include "checks.h" from the build directory
    files = {"schemas.cpp": schemas((CSRC / "t3fast.cpp").read_text()),
             "checks.h": rewrite_checks((CSRC / "checks.h").read_text()),
             "triplane_args.cpp": (CSRC / "triplane_args.cpp").read_text()}
    for kernel in [*sorted((CSRC / "cuda").glob("*_kernel.cu")), HERE / "selftest_kernel.cu"]:
        files[kernel.stem + ".cpp"] = rewrite_kernels(kernel.read_text())
    for glue in sorted((CSRC / "cuda").glob("*.cpp")):
        if glue.name != "stream.cpp":  # the emulator's stream comes from harness.cpp
            files["glue_" + glue.name] = rewrite_glue(glue.read_text())
    return files


@cache
def load() -> object:
    """Builds (once per content, in the temporary directory) and loads the emulated CUDA
    operators: afterwards ``torch.ops.t3fast_emu`` holds them. Returns the harness's operators
    (``torch.ops.t3fast_emu_harness``): ``selftest(name, input)`` runs one of the emulator's
    self-test kernels, ``set_compute_capability(major)`` sets what the emulated device reports."""
    from torch.utils.cpp_extension import load as load_extension

    files = _generated()
    fixed = [HERE / "harness.cpp"]
    inputs = [*fixed, Path(__file__), *sorted((HERE / "include").iterdir()), *sorted(CSRC.glob("*.h")),
              *sorted((CSRC / "cuda").glob("*.h")), *sorted((CSRC / "cuda").glob("*.cuh"))]
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in inputs)
                            + "".join(files.values()).encode()).hexdigest()[:16]
    build = Path(tempfile.gettempdir()) / f"t3fast_cuda_emulation_{digest}"
    build.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        if not (build / name).exists() or (build / name).read_text() != text:
            (build / name).write_text(text)
    sources = [str(p) for p in fixed] + [str(build / name) for name in files if name.endswith(".cpp")]
    load_extension(name=f"t3fast_cuda_emulation_{digest}", sources=sources, build_directory=str(build),
                   extra_include_paths=[str(build), str(HERE / "include"), str(CSRC)],
                   # a misaligned vector load (a float4 off its 16 bytes) faults on a GPU: here
                   # UBSan's alignment check aborts with the file and line; kernels read shared
                   # memory as other types than they wrote it (as CUDA allows)
                   extra_cflags=["-O2", "-ffp-contract=off", "-fno-strict-aliasing", "-fsanitize=alignment",
                                 "-fno-sanitize-recover=alignment"],
                   extra_ldflags=["-fsanitize=alignment"], is_python_module=False, verbose=False)
    return torch.ops.t3fast_emu_harness


@contextmanager
def emulated_ops() -> Iterator[None]:
    """Inside, t3fast's public operators (``t3fast.ops.*``, which the models call) run the
    emulated CUDA operators on CPU tensors. Combined with :func:`t3fast.host_syncs.sync_free`,
    a model runs as it does on a GPU."""
    import t3fast.ops as public

    load()
    saved = public.ops
    public.ops = torch.ops.t3fast_emu
    try:
        yield
    finally:
        public.ops = saved
