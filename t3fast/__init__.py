"""t3fast: the Delta-Triplane occupancy world model (T3Former) with fused C++/CUDA operators.

Heavy pieces (the compiled operators, the models) load on first use, so that
``import t3fast.data`` or the command line start quickly.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> module that defines it
_LAZY = {
    "build_info": "t3fast.ops",
    "triplane_decode": "t3fast.ops",
    "axis_pool": "t3fast.ops",
    "delta_fuse": "t3fast.ops",
    "Triplane": "t3fast.models",
    "TriplaneAutoencoder": "t3fast.models",
    "TriplaneDecoder": "t3fast.models",
    "TriplaneEncoder": "t3fast.models",
    "T3Former": "t3fast.models.world_model",
    "Forecast": "t3fast.models.world_model",
    "load_world_model": "t3fast.pretrained",
    "load_autoencoder": "t3fast.pretrained",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 't3fast' has no attribute '{name}'")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(list(globals()) + list(_LAZY))


__all__ = ["__version__", *_LAZY]
