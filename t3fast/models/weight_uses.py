"""A module's weights used several times in one differentiated forward (the steps of a rollout,
the planes through a shared network), their gradients summed in a few multi-tensor ops.

Autograd sums the gradients of a tensor used k times with k - 1 adds of that tensor: a
forecaster of 878 weight tensors rolled out over 6 steps makes 4,390 small kernels in every
training step. Here each use reads its own alias of the weights, all made by one autograd node
whose backward sums the uses' gradients with ``torch._foreach_add`` (on a GPU a few launches per
use for all the weights together). The values are the same; the sums are in use order, so they
may differ from autograd's in the last bits.

Under autocast the weights of the layers autocast runs in low precision (linear, convolution,
attention projections) are cast once and the casts aliased, as autocast's own cache of leaf
weights would: an alias is no leaf, and autocast would cast it again at every use. So it suits
modules whose layers run as themselves; not the decoder, whose fused op reads its layers'
float32 weights and decodes in their dtype.

    uses = weights_per_use(net, len(planes))
    features = [call_with(net, weights, plane) for weights, plane in zip(uses, planes)]
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn


class _Aliases(torch.autograd.Function):
    """``uses`` aliases of each weight; backward: each weight's gradients summed over its uses."""

    @staticmethod
    def forward(ctx, uses: int, *weights: Tensor) -> tuple[Tensor, ...]:
        ctx.uses, ctx.count = uses, len(weights)
        return tuple(w.view_as(w) for _ in range(uses) for w in weights)

    @staticmethod
    def backward(ctx, *grads: Tensor) -> tuple[Tensor | None, ...]:
        n = ctx.count
        per_use = [list(grads[u * n : (u + 1) * n]) for u in range(ctx.uses)]
        total = torch._foreach_add(per_use[0], per_use[1])
        for more in per_use[2:]:
            torch._foreach_add_(total, more)
        return (None, *total)


#: layers whose weights autocast casts to its low-precision type
_LOW_PRECISION_LAYERS = (nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d, nn.MultiheadAttention)


def _autocast_casts(module: nn.Module, weights: list[Tensor]) -> list[Tensor]:
    """``weights``, those autocast would cast (if it is on) cast once to its type."""
    device_type = weights[0].device.type
    if not torch.is_autocast_enabled(device_type):
        return weights
    dtype = torch.get_autocast_dtype(device_type)
    low = {id(w) for layer in module.modules() if isinstance(layer, _LOW_PRECISION_LAYERS)
           for w in layer.parameters(recurse=False)}
    return [w.to(dtype) if id(w) in low and w.dtype == torch.float32 else w for w in weights]


def weights_per_use(module: nn.Module, uses: int) -> list[dict[str, Tensor] | None]:
    """One dict of ``module``'s trainable weights (name -> alias) for each of its ``uses`` calls,
    to pass to :func:`call_with`. Each is None (the module's own weights) where aliases would
    not help: a single use, no gradient being recorded, or no trainable weight."""
    named = [(name, w) for name, w in module.named_parameters() if w.requires_grad]
    if uses < 2 or not named or not torch.is_grad_enabled():
        return [None] * uses
    names = [name for name, _ in named]
    aliases = _Aliases.apply(uses, *_autocast_casts(module, [w for _, w in named]))
    return [dict(zip(names, aliases[u * len(names) : (u + 1) * len(names)])) for u in range(uses)]


def call_with(module: nn.Module, weights: dict[str, Tensor] | None, *args: Any, **kwargs: Any) -> Any:
    """``module(*args, **kwargs)`` with ``weights`` (one use's, from :func:`weights_per_use`) in
    place of its own, or with its own where ``weights`` is None."""
    if weights is None:
        return module(*args, **kwargs)
    return torch.func.functional_call(module, weights, args, kwargs)
