"""Shared test fixtures: the devices every op test runs on."""

from __future__ import annotations

import pytest
import torch


def _cuda_built() -> bool:
    try:
        import t3fast.ops

        return bool(t3fast.ops.build_info()["cuda"])
    except ImportError:
        return False


HAS_CUDA = torch.cuda.is_available() and _cuda_built()

DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=[
            pytest.mark.cuda,
            pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA build of t3fast and a GPU"),
        ],
    ),
]


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param
