"""Loads the compiled extension ``t3fast._C``, or tells why it cannot be used.

An extension that is missing, fails to load, or was compiled against another torch (its
operators would then crash or misbehave) is not used: the ops then run through their
pure-PyTorch references.
"""

from __future__ import annotations

from types import ModuleType

import torch

BUILD_HINT = "build the extension with `pip install --no-build-isolation -e .` (needs a C++ compiler and ninja)"


def _load() -> tuple[ModuleType | None, str | None]:
    """``(extension, None)``, or ``(None, why it cannot be used)``."""
    try:
        from t3fast import _C
    except ImportError as exc:
        return None, f"t3fast._C cannot be imported: {exc}"
    built = _C.build_info()["torch_version"]
    running = torch.__version__.split("+")[0]
    if built.split(".")[:2] != running.split(".")[:2]:
        return None, f"t3fast._C was compiled against torch {built} but torch {running} is running"
    return _C, None


_C, UNAVAILABLE_REASON = _load()
