"""Moving a feature plane by a flow field: the motion part of the flow forecaster.

A flow is backward: ``flow[:, :, i, j]`` says where, in plane cells, the content that ends up
at cell ``(i, j)`` comes from (``(d_i, d_j)``, along dims -2 and -1 of the plane), so the
moved plane is one bilinear lookup per cell (``F.grid_sample``, ``align_corners=False``, the
same cell-centre convention as the decoder's plane lookups) and gradients reach the flow.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F


def cell_grid(h: int, w: int, device: torch.device, dtype: torch.dtype = torch.float32) -> Tensor:
    """Cell centres ``[h, w, 2]`` in plane cells: ``(i, j)``."""
    i = torch.arange(h, device=device, dtype=dtype)
    j = torch.arange(w, device=device, dtype=dtype)
    return torch.stack(torch.meshgrid(i, j, indexing="ij"), dim=-1)


def warp_plane(plane: Tensor, flow: Tensor) -> Tensor:
    """``plane`` ``[B, C, H, W]`` moved by the backward ``flow`` ``[B, 2, H, W]`` (plane cells):
    ``out[:, :, i, j] = plane at (i + flow_i, j + flow_j)``, bilinear; beyond the edge the
    edge's value (the plane continues)."""
    b, _, h, w = plane.shape
    if flow.shape != (b, 2, h, w):
        raise ValueError(f"warp_plane: flow must have shape {[b, 2, h, w]}, got {list(flow.shape)}")
    pos = cell_grid(h, w, plane.device, flow.dtype) + flow.permute(0, 2, 3, 1)  # [B, H, W, (i, j)]
    # grid_sample's grid is (x = along W, y = along H) in [-1, 1] at the outer cell edges
    norm = torch.stack([(2 * pos[..., 1] + 1) / w - 1, (2 * pos[..., 0] + 1) / h - 1], dim=-1)
    return F.grid_sample(plane, norm.to(plane.dtype), mode="bilinear", padding_mode="border", align_corners=False)
