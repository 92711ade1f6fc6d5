"""Builds the t3fast._C extension: CPU kernels always, CUDA kernels when possible.

CUDA is built when torch itself is a CUDA build (torch.version.cuda) and a CUDA toolkit is
found (CUDA_HOME), never by probing for a GPU, so a wheel built on a GPU-less build box still
carries the CUDA kernels. FORCE_CUDA=1 forces the CUDA build, T3FAST_NO_CUDA=1 disables it.
"""

import glob
import os

import torch
from setuptools import setup
from torch.utils.cpp_extension import CUDA_HOME, BuildExtension, CppExtension, CUDAExtension

ROOT = os.path.dirname(os.path.abspath(__file__))


def _with_cuda() -> bool:
    if os.environ.get("T3FAST_NO_CUDA", "0") == "1":
        return False
    if os.environ.get("FORCE_CUDA", "0") == "1":
        return True
    return torch.version.cuda is not None and CUDA_HOME is not None


def _sources(pattern: str) -> list[str]:
    return sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, pattern)))


def _extension():
    with_cuda = _with_cuda()
    sources = _sources("csrc/*.cpp") + _sources("csrc/cpu/*.cpp")
    cxx = ["-O3", "-fopenmp"]  # the C++ standard is the one torch asks for
    macros = []
    if with_cuda:
        sources += _sources("csrc/cuda/*.cpp") + _sources("csrc/cuda/*.cu")
        major, minor = (int(v) for v in torch.version.cuda.split(".")[:2])
        macros += [
            ("T3FAST_WITH_CUDA", "1"),
            ("T3FAST_CUDA_VERSION", str(major * 1000 + minor * 10)),
        ]
        nvcc = ["-O3", "--expt-relaxed-constexpr"]
        return CUDAExtension(
            "t3fast._C",
            sources,
            include_dirs=[os.path.join(ROOT, "csrc")],
            define_macros=macros,
            extra_compile_args={"cxx": cxx, "nvcc": nvcc},
            extra_link_args=["-fopenmp"],
        )
    return CppExtension(
        "t3fast._C",
        sources,
        include_dirs=[os.path.join(ROOT, "csrc")],
        define_macros=macros,
        extra_compile_args={"cxx": cxx},
        extra_link_args=["-fopenmp"],
    )


setup(
    ext_modules=[_extension()],
    cmdclass={"build_ext": BuildExtension.with_options(use_ninja=True)},
)
