"""Pre-norm Transformer encoder/decoder layers sized for many short token sequences.

The forecaster's fine scales run temporal attention: tens of thousands of sequences of at
most ``history`` (5) tokens. ``nn.MultiheadAttention`` spends most of that time in
layout copies and in the CPU flash-attention kernel, which is built for long sequences;
for short ones an explicit ``einsum`` + softmax is several times faster forward and
backward. Long sequences (the coarse scales' full attention) still go through
``F.scaled_dot_product_attention``, and so does every sequence on a GPU, where one fused
attention kernel replaces the explicit path's eight (copies, two batched products, scaling,
softmax) and its backward's sixteen: a tenth of the launches of a paper-size training step.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

SHORT = 16  # on the CPU, key lengths up to this (or a single query) use the explicit einsum path


def explicit_attention(queries: int, keys: int, device: torch.device) -> bool:
    """Whether attention of ``queries`` over ``keys`` tokens on ``device`` runs as an explicit
    einsum + softmax (short sequences on the CPU) rather than ``F.scaled_dot_product_attention``."""
    return device.type == "cpu" and (keys <= SHORT or queries == 1)


class Attention(nn.Module):
    """Multi-head attention ``[N, Tq, D] x [N, Tk, D] -> [N, Tq, D]``."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} is not divisible by heads {heads}")
        self.heads = heads
        self.q, self.k, self.v, self.out = (nn.Linear(dim, dim) for _ in range(4))

    def forward(self, x: Tensor, context: Tensor) -> Tensor:
        n, tq, d = x.shape
        tk, h = context.shape[1], self.heads
        # the projections of one input as one GEMM (the same values): in the backward one GEMM
        # per operand instead of three, and no adds of the input's three gradients
        if context is x:
            q, k, v = _projections(x, self.q, self.k, self.v).view(n, tq, 3, h, d // h).unbind(2)
        else:
            q = self.q(x).view(n, tq, h, d // h)
            k, v = _projections(context, self.k, self.v).view(n, tk, 2, h, d // h).unbind(2)
        if explicit_attention(tq, tk, x.device):
            scores = torch.einsum("nqhd,nkhd->nhqk", q, k) * (1.0 / math.sqrt(d // h))
            out = torch.einsum("nhqk,nkhd->nqhd", scores.softmax(dim=-1), v)
        else:
            out = F.scaled_dot_product_attention(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2))
            out = out.transpose(1, 2)
        return self.out(out.reshape(n, tq, d))


def _projections(x: Tensor, *layers: nn.Linear) -> Tensor:
    """``torch.cat([layer(x) for layer in layers], -1)`` as one GEMM."""
    weight = torch.cat([layer.weight for layer in layers])
    bias = torch.cat([layer.bias for layer in layers])
    return F.linear(x, weight, bias)


class TransformerLayer(nn.Module):
    """Pre-norm layer: self-attention, cross-attention to ``memory`` (decoder layers only),
    MLP with ``mlp_ratio * dim`` hidden units; residual around each."""

    def __init__(self, dim: int, heads: int, mlp_ratio: int = 2, cross: bool = False):
        super().__init__()
        self.norm_self = nn.LayerNorm(dim)
        self.attn_self = Attention(dim, heads)
        self.norm_cross = nn.LayerNorm(dim) if cross else None
        self.attn_cross = Attention(dim, heads) if cross else None
        self.norm_mlp = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, mlp_ratio * dim), nn.GELU(), nn.Linear(mlp_ratio * dim, dim))

    def forward(self, x: Tensor, memory: Tensor | None = None) -> Tensor:
        y = self.norm_self(x)
        x = x + self.attn_self(y, y)
        if self.attn_cross is not None:
            x = x + self.attn_cross(self.norm_cross(x), memory)
        return x + self.mlp(self.norm_mlp(x))


class TransformerStack(nn.Module):
    """``layers`` encoder layers (``cross=False``) or decoder layers (``cross=True``), then a norm."""

    def __init__(self, dim: int, heads: int, layers: int, mlp_ratio: int = 2, cross: bool = False):
        super().__init__()
        self.layers = nn.ModuleList(TransformerLayer(dim, heads, mlp_ratio, cross) for _ in range(layers))
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: Tensor, memory: Tensor | None = None) -> Tensor:
        for layer in self.layers:
            x = layer(x, memory)
        return self.norm(x)
