"""Load info pickles without running code from them.

``pickle.load`` calls whatever the file names, so a downloaded info file could run a shell
command. :func:`load_restricted` accepts only what info files hold: dicts, lists, tuples,
strings, bytes, numbers, booleans, None, numpy arrays and numpy scalars. Anything else is a
:class:`~t3fast.errors.DataFormatError` raised before the object is built.
"""

from __future__ import annotations

import _codecs
import importlib
import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from t3fast.errors import DataFormatError


def _numpy_module(name: str) -> Any:
    """``numpy._core.<name>`` (numpy 2) or ``numpy.core.<name>`` (numpy 1), whichever exists."""
    try:
        return importlib.import_module(f"numpy._core.{name}")
    except ImportError:
        return importlib.import_module(f"numpy.core.{name}")


def _allowed_globals() -> dict[tuple[str, str], Any]:
    multiarray, numeric = _numpy_module("multiarray"), _numpy_module("numeric")
    allowed: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        # protocol 2 pickles spell bytes as _codecs.encode(str, "latin1")
        ("_codecs", "encode"): _codecs.encode,
    }
    # files written under numpy 1 name numpy.core, under numpy 2 numpy._core
    for package in ("numpy.core", "numpy._core"):
        allowed[(f"{package}.multiarray", "_reconstruct")] = multiarray._reconstruct
        allowed[(f"{package}.multiarray", "scalar")] = multiarray.scalar
        allowed[(f"{package}.numeric", "_frombuffer")] = numeric._frombuffer
    return allowed


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that resolves only the numpy array and scalar constructors."""

    _allowed = _allowed_globals()

    def find_class(self, module: str, name: str) -> Any:
        try:
            return self._allowed[(module, name)]
        except KeyError:
            raise DataFormatError(
                f"refusing to load {module}.{name}: info pickles may hold only dicts, lists, tuples, "
                "strings, numbers, booleans, None and numpy arrays"
            ) from None


def load_restricted(path: str | Path) -> Any:
    """Unpickle ``path`` with :class:`RestrictedUnpickler`; every failure is a ``DataFormatError``
    naming the file."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataFormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    try:
        return RestrictedUnpickler(io.BytesIO(data)).load()
    except DataFormatError as exc:
        raise DataFormatError(f"{path}: {exc}") from None
    except Exception as exc:  # any other unpickling failure means the file is not an info pickle
        raise DataFormatError(f"{path}: not a readable pickle ({type(exc).__name__}: {exc})") from exc
