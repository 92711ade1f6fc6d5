"""Argument checks the C++ glue cannot make: Python integers too large for int64, and outputs
too large for the device, refused with a message instead of a cast error or an allocator failure."""

from __future__ import annotations

import operator
import os
from collections.abc import Sequence

import torch


def device_memory_bytes(device: torch.device) -> int | None:
    """Total memory of ``device`` (physical RAM for the CPU); None where it cannot be told."""
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory
    if device.type == "cpu" and hasattr(os, "sysconf"):
        try:
            return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError):
            return None
    return None


def _human(nbytes: int) -> str:
    size = float(nbytes)
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if size < 1024 or unit == "PB":
            return f"{size:.1f} {unit}"
        size /= 1024
    raise AssertionError("unreachable")


def checked_grid(grid: Sequence[int], xy: torch.Tensor, classes: int, argmax: bool) -> list[int]:
    """``grid`` as ints after checking that the full-grid output fits in memory.

    The output holds ``B * X * Y * Z`` uint8 labels (``argmax``) or ``B * X * Y * Z * classes``
    values of ``xy``'s dtype.
    """
    try:
        sizes = [operator.index(n) for n in grid]
    except TypeError:
        raise ValueError(f"t3fast.triplane_decode: grid must hold integers, got {tuple(grid)!r}") from None
    if any(abs(n) >= 2**63 for n in sizes):
        raise ValueError(f"t3fast.triplane_decode: grid sizes must fit in 64 bits, got {tuple(sizes)}")
    if len(sizes) != 3 or any(n < 0 for n in sizes):
        return sizes  # the compiled op names these mistakes
    if torch.compiler.is_compiling():
        return sizes  # the memory query cannot be traced; eager calls check it
    per_voxel = 1 if argmax else classes * xy.element_size()
    nbytes = xy.shape[0] * sizes[0] * sizes[1] * sizes[2] * per_voxel
    limit = device_memory_bytes(xy.device)
    if limit is not None and nbytes > limit:
        what = "labels" if argmax else f"logits of {classes} classes"
        raise ValueError(
            f"t3fast.triplane_decode: grid {tuple(sizes)} at batch {xy.shape[0]} needs {_human(nbytes)} of "
            f"{what}, more than the {_human(limit)} of memory on {xy.device}"
        )
    return sizes
