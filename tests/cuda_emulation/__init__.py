"""t3fast's CUDA kernels run on the CPU by an emulator, for testing them without a GPU.

The kernel files (``csrc/cuda/*_kernel.cu``) are compiled by the host compiler against the
headers in ``include/``, which stand in for the CUDA runtime, ``cuda_fp16.h``, ``cuda_bf16.h``
and WMMA (``mma.h``): a block's threads run as fibers with real barriers, shared memory is
per block with guard bytes, WMMA products round as the tensor cores do, and misuse (divergent
barriers, misaligned fragment loads, overrunning shared memory, a launch asking for more
shared memory than it opted into) fails the launch with a message. The only rewriting is
mechanical: ``kernel<<<grid, block, smem, stream>>>(args)`` becomes a call, and the dynamic
``extern __shared__`` buffer a pointer. ``harness.cpp`` calls the launchers as the CUDA glue
does. What it cannot show: speed, the hardware's memory model beyond barriers (blocks run one
at a time), and warp-synchronous code without barriers.
"""

from __future__ import annotations

import hashlib
import re
import tempfile
from functools import cache
from pathlib import Path
from types import ModuleType

HERE = Path(__file__).resolve().parent
CSRC = HERE.parents[1] / "csrc"
KERNELS = ("triplane_decode_kernel.cu", "triplane_decode_mma_kernel.cu")

_SHARED = re.compile(r"extern\s+__shared__\s+__align__\(\d+\)\s+unsigned char\s+(\w+)\[\];")
_LAUNCH = re.compile(r"([A-Za-z_][\w:]*(?:<[^;{}<>]*>)?)<<<(.*?)>>>", re.DOTALL)
_PRELUDE = "#define __CUDACC__ 1\n#define __CUDA_ARCH__ 900\n#include <cuda_runtime.h>\n"


def rewrite(source: str) -> str:
    """A kernel file as host C++ for the emulator (see the module docstring)."""
    source = _SHARED.sub(r"unsigned char* \1 = ::t3emu::dynamic_smem();", source)
    source = _LAUNCH.sub(r"::t3emu::launch(\1, \2)", source)
    return _PRELUDE + source


@cache
def load() -> ModuleType:
    """The emulated kernels' module (built once per content, in the temporary directory)."""
    from torch.utils.cpp_extension import load as load_extension

    inputs = [HERE / "harness.cpp", HERE / "selftest_kernel.cu", *sorted((HERE / "include").iterdir()), Path(__file__),
              *(CSRC / "cuda" / k for k in KERNELS), CSRC / "cuda" / "kernels.h",
              CSRC / "cuda" / "triplane_sample.cuh"]
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in inputs)).hexdigest()[:16]
    build = Path(tempfile.gettempdir()) / f"t3fast_cuda_emulation_{digest}"
    build.mkdir(parents=True, exist_ok=True)
    sources = [str(HERE / "harness.cpp")]
    for kernel in [*(CSRC / "cuda" / k for k in KERNELS), HERE / "selftest_kernel.cu"]:
        target = build / (kernel.stem + ".cpp")
        target.write_text(rewrite(kernel.read_text()))
        sources.append(str(target))
    return load_extension(name=f"t3fast_cuda_emulation_{digest}", sources=sources, build_directory=str(build),
                          extra_include_paths=[str(HERE / "include"), str(CSRC)],
                          extra_cflags=["-O2", "-std=c++17"], verbose=False)
