"""AdamW parameter groups: which parameters decay, and per-part learning rates."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import nn


def param_groups(
    model: nn.Module, weight_decay: float, lr: float | None = None, lr_scales: Mapping[str, float] | None = None
) -> list[dict[str, Any]]:
    """AdamW groups: decay on weight matrices/kernels; none on biases, norm weights (every 1-D
    parameter) and embedding tables. Frozen parameters are left out.

    ``lr_scales`` maps submodule names (``"decoder"``) to learning-rate multipliers; their
    parameters get groups of their own with ``lr = lr * scale``. Groups at the full rate come
    first (decay, then no decay)."""
    scales = dict(lr_scales or {})
    groups: dict[tuple[float, bool], list[nn.Parameter]] = {}
    seen: set[int] = set()
    for name, module in model.named_modules():
        scale = next((s for prefix, s in scales.items() if name == prefix or name.startswith(prefix + ".")), 1.0)
        for p in module.parameters(recurse=False):
            if not p.requires_grad or id(p) in seen:  # shared parameters appear once
                continue
            seen.add(id(p))
            exempt = p.ndim < 2 or isinstance(module, nn.Embedding | nn.EmbeddingBag)
            groups.setdefault((scale, exempt), []).append(p)
    ordered = sorted(groups, key=lambda key: (key[0] != 1.0, -key[0], key[1]))
    return [
        {"params": groups[key], "weight_decay": 0.0 if key[1] else weight_decay}
        | ({} if lr is None else {"lr": lr * key[0]})
        for key in ordered
    ]
