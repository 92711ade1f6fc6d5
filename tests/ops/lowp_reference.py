"""The arithmetic of the CUDA triplane_decode in a low precision, in plain PyTorch (any device),
and upstream gradients that keep gradient comparisons away from the ReLU kinks.

The CUDA op computes its MLP in a dtype ``dtype`` (float16 / bfloat16, the autocast dtype, or
float32): the plane lookups and the encoding in float32, rounded to ``dtype``; the weights and
biases rounded to ``dtype``; products accumulated in float32; every hidden layer's output
(bias and ReLU in float32) rounded to ``dtype``. Its backward recomputes the layers the same way
and rounds the upstream gradient and each propagated gradient ``G W`` to ``dtype``, accumulating
the weight, bias and plane gradients in float32. :func:`rounded_decode` does exactly these
roundings on float32 tensors, so the kernels match it up to float32 summation order and the
final rounding of their outputs.

A gradient of a ReLU network is discontinuous where a hidden pre-activation is zero: two correct
float32 computations that differ in the last bits can land on opposite sides of a kink and
disagree by a whole hidden unit's contribution (a test in float16 once failed this way, one
pre-activation of 3.3e-7 giving 7 plane-gradient values off by 0.22).
:func:`kink_free_upstream` zeroes the upstream gradient of every point that comes within a
margin of a kink, so that the compared gradients are continuous functions of the inputs.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from t3fast.ops import reference


class _Round(torch.autograd.Function):
    """Rounds to ``dtype`` (keeping the tensor's own dtype) the values (``values``) and the
    gradient (``grad``)."""

    @staticmethod
    def forward(ctx, x: Tensor, dtype: torch.dtype, values: bool, grad: bool) -> Tensor:
        ctx.dtype, ctx.grad = dtype, grad
        return x.to(dtype).to(x.dtype) if values else x.clone()

    @staticmethod
    def backward(ctx, g: Tensor):
        return (g.to(ctx.dtype).to(g.dtype) if ctx.grad else g), None, None, None


def _round(x: Tensor, dtype: torch.dtype, values: bool = True, grad: bool = True) -> Tensor:
    return x if dtype == x.dtype else _Round.apply(x, dtype, values, grad)


def rounded_decode(
    xy: Tensor,
    xz: Tensor,
    yz: Tensor,
    weights: Sequence[Tensor],
    biases: Sequence[Tensor],
    *,
    dtype: torch.dtype,
    grid: Sequence[int] | None = None,
    points: Tensor | None = None,
    pe_freqs: int = 6,
    preacts: list[Tensor] | None = None,
) -> Tensor:
    """Logits of ``t3fast.ops.reference.triplane_decode`` on float32 inputs with the CUDA op's
    roundings to ``dtype`` (module docstring); differentiable with the backward's roundings.
    ``preacts``, when given, receives every hidden layer's pre-activation ``[B, N, width]``."""
    batch = xy.shape[0]
    if grid is not None:
        query = reference.grid_coordinates(grid, device=xy.device, dtype=xy.dtype).reshape(1, -1, 3)
        query, out_shape = query.expand(batch, -1, -1), (batch, *grid)
    else:
        query, out_shape = points, tuple(points.shape[:2])
    h = _round(reference.triplane_features(xy, xz, yz, query, pe_freqs), dtype)
    for i, (w, b) in enumerate(zip(weights, biases)):
        z = F.linear(h, _round(w, dtype, grad=False), _round(b, dtype, grad=False))
        if i + 1 < len(weights):
            if preacts is not None:
                preacts.append(z.detach())
            h = _round(torch.relu(z), dtype)
    # fp32 logits; the backward starts from the upstream gradient rounded to dtype
    logits = _round(z, dtype, values=False)
    return logits.reshape(*out_shape, logits.shape[-1])


def kink_free_upstream(upstream: Tensor, preacts: Sequence[Tensor], margin: float) -> Tensor:
    """``upstream`` ``[B, ..., K]`` with the rows of the points zeroed whose hidden
    pre-activations (``[B, N, width]`` each) come within ``margin`` times that layer's RMS of
    zero, where the ReLU's derivative jumps."""
    near = torch.zeros(preacts[0].shape[:2], dtype=torch.bool, device=upstream.device)
    for z in preacts:
        rms = z.float().pow(2).mean().sqrt()
        near |= (z.abs() < margin * rms).any(-1)
    keep = (~near).reshape(*upstream.shape[:-1], 1)
    return upstream * keep.to(upstream.dtype)
