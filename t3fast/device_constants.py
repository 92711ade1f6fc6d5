"""Constants made once per device. On a GPU, a tensor made from host data (``torch.tensor``,
``new_tensor``, ``torch.from_numpy(...).to(device)``) is a copy that waits for the device, and a
CUDA graph cannot capture one; made once and kept, it is a read at every later call.

Inside a graph that ``torch.compile`` traces, the tensors are made in place instead: the graph
holds them as its constants. The kept tensors are shared: never write to them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import TypeVar

import torch
from torch import Tensor

T = TypeVar("T")


def made_once(make: Callable[..., T]) -> Callable[..., T]:
    """Decorator: ``make(*args)`` (hashable arguments, a device among them) runs once per
    arguments and its result is kept; made outside inference mode and autograd, so that training
    code may read it too. While ``torch.compile`` traces, ``make`` runs each time."""

    @functools.lru_cache(maxsize=256)
    def kept(*args: object) -> T:
        with torch.inference_mode(False), torch.no_grad():
            return make(*args)

    @functools.wraps(make)
    def get(*args: object) -> T:
        return make(*args) if torch.compiler.is_compiling() else kept(*args)

    return get


@made_once
def _constant(values: tuple, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor(values, dtype=dtype, device=device)


def device_constant(values: Sequence, dtype: torch.dtype, device: torch.device | str) -> Tensor:
    """``torch.tensor(values, dtype=dtype, device=device)``, made once per device (read-only):
    ``values`` a flat sequence of numbers."""
    return _constant(tuple(values), dtype, torch.device(device))
