"""Convolution building blocks of the autoencoder."""

from __future__ import annotations

from torch import Tensor, nn

from t3fast.ops import group_norm_silu


def group_norm(channels: int) -> nn.GroupNorm:
    # GroupNorm works at batch size 1 and 2, the usual sizes for 200x200x16 volumes.
    return nn.GroupNorm(min(8, channels), channels)


def norm_silu(norm: nn.GroupNorm, act: nn.SiLU, x: Tensor, residual: Tensor | None = None,
              fused: bool = True) -> Tensor:
    """``act(norm(x) + residual)`` (``residual`` None: ``act(norm(x))``), ``[B, C, *]`` in and
    out: one :func:`~t3fast.ops.group_norm_silu` (``fused``) or the modules one after another
    (``x`` then is overwritten: the activation runs in place)."""
    if fused:
        return group_norm_silu(x, norm.weight, norm.bias, norm.num_groups, norm.eps, residual)
    out = norm(x)
    if residual is not None:
        out += residual
    return act(out)


class ResBlock3d(nn.Module):
    """``x + conv-norm-act-conv-norm(x)``, then an activation; ``[B, C, X, Y, Z]`` in and out.
    Each norm and the activation after it run as one op (:func:`norm_silu`) unless ``fused`` is
    False."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv3d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
            nn.SiLU(inplace=True),  # in place: a fresh 3D activation costs its page faults on the CPU
            nn.Conv3d(channels, channels, 3, padding=1, bias=False),
            group_norm(channels),
        )
        self.act = nn.SiLU(inplace=True)

    def forward(self, x: Tensor, fused: bool = True) -> Tensor:
        conv1, norm1, act1, conv2, norm2 = self.body
        out = norm_silu(norm1, act1, conv1(x), fused=fused)
        return norm_silu(norm2, self.act, conv2(out), residual=x, fused=fused)


class PlaneRefiner(nn.Module):
    """Per-plane 2D refinement ``[B, C_in, H, W] -> [B, C_out, H, W]``: conv-act-conv."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(in_channels, out_channels, 3, padding=1),
            nn.SiLU(),
            nn.Conv2d(out_channels, out_channels, 3, padding=1),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.body(x)
