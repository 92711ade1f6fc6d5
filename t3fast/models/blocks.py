"""Convolution building blocks of the autoencoder."""

from __future__ import annotations

from torch import Tensor, nn


def group_norm(channels: int) -> nn.GroupNorm:
    # GroupNorm works at batch size 1 and 2, the usual sizes for 200x200x16 volumes.
    return nn.GroupNorm(min(8, channels), channels)


class ResBlock3d(nn.Module):
    """``x + conv-norm-act-conv-norm(x)``, then an activation; ``[B, C, X, Y, Z]`` in and out."""

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

    def forward(self, x: Tensor) -> Tensor:
        out = self.body(x)
        out += x
        return self.act(out)


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
