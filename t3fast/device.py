"""Which device a command runs on."""

from __future__ import annotations

import os
import re

import torch

from t3fast.errors import ConfigError

#: the values of a ``device`` setting of training (torchrun gives each process its own GPU)
DEVICE_NAMES = ("auto", "cuda", "cpu")


def default_device() -> torch.device:
    """CUDA when available, else the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def check_device_name(value: object, key: str) -> None:
    """Raise :class:`~t3fast.errors.ConfigError` naming ``key`` unless ``value`` is one of
    :data:`DEVICE_NAMES`; ``cuda:N`` gets a pointer to ``CUDA_VISIBLE_DEVICES``."""
    if value in DEVICE_NAMES:
        return
    hint = ""
    indexed = re.fullmatch(r"cuda:(\d+)", str(value))
    if indexed:
        hint = f" (each process trains on one GPU: choose it with CUDA_VISIBLE_DEVICES={indexed[1]})"
    raise ConfigError(f"{key} must be {', '.join(map(repr, DEVICE_NAMES[:-1]))} or {DEVICE_NAMES[-1]!r}, "
                      f"got {value!r}{hint}")


def require_device(value: str, key: str) -> str:
    """``value`` (one of :data:`DEVICE_NAMES`) once this machine is known to have it.

    ``"cuda"`` needs CUDA and, for the process of local rank ``LOCAL_RANK`` (torchrun), that
    many GPUs and one more; otherwise :class:`~t3fast.errors.ConfigError` names ``key``.
    """
    check_device_name(value, key)
    if value != "cuda":
        return value
    if not torch.cuda.is_available():
        raise ConfigError(f"{key} is 'cuda' but CUDA is not available here: use {key}=cpu (or auto)")
    local_rank, count = int(os.environ.get("LOCAL_RANK", "0")), torch.cuda.device_count()
    if local_rank >= count:
        raise ConfigError(f"{key} is 'cuda' but this process (LOCAL_RANK={local_rank}) needs GPU {local_rank} "
                          f"and {count} are visible: start at most {count} processes per machine")
    return value
