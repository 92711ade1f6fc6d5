"""Moving a feature plane by a flow field, and finding motion between planes: the flow forecaster's parts.

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


def splat_plane(values: Tensor, displacement: Tensor) -> Tensor:
    """Forward splatting: each cell's ``values`` ``[B, V, H, W]`` sent to its cell plus
    ``displacement`` ``[B, 2, H, W]`` (plane cells, ``(d_i, d_j)``) and spread over the four
    nearest cells with bilinear weights, which are summed where several land (what lands
    beyond the edge is dropped). Gradients reach both the values and the displacement."""
    b, v, h, w = values.shape
    if displacement.shape != (b, 2, h, w):
        raise ValueError(f"splat_plane: displacement must have shape {[b, 2, h, w]}, got {list(displacement.shape)}")
    pos = cell_grid(h, w, values.device, displacement.dtype) + displacement.permute(0, 2, 3, 1)  # [B, H, W, 2]
    base = pos.detach().floor()
    frac = pos - base  # carries the gradient to the displacement
    base = base.long()
    flat = values.reshape(b, v, h * w)
    out = values.new_zeros(b, v, h * w)
    for di in (0, 1):
        for dj in (0, 1):
            i, j = base[..., 0] + di, base[..., 1] + dj
            weight = (frac[..., 0] if di else 1 - frac[..., 0]) * (frac[..., 1] if dj else 1 - frac[..., 1])
            inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
            index = (i.clamp(0, h - 1) * w + j.clamp(0, w - 1)).view(b, 1, h * w).expand(-1, v, -1)
            out = out.scatter_add(2, index, flat * (weight * inside).view(b, 1, h * w).to(values.dtype))
    return out.view(b, v, h, w)


def matching_costs(present: Tensor, previous: Tensor, radius: int) -> Tensor:
    """How well each cell of ``present`` ``[B, C, H, W]`` matches the cells of ``previous`` around
    it: ``out[:, n]`` is minus the channel-mean absolute difference to ``previous`` shifted by
    the n-th ``(d_i, d_j)`` of ``[-radius, radius]^2`` (row-major), ``[B, (2r+1)^2, H, W]``.
    The best match sits where the content came from: a local, data-independent view of motion."""
    h, w = present.shape[-2:]
    padded = F.pad(previous, (radius,) * 4, mode="replicate")
    size = 2 * radius + 1
    costs = [
        -(present - padded[..., di : di + h, dj : dj + w]).abs().mean(1)
        for di in range(size)
        for dj in range(size)
    ]
    return torch.stack(costs, dim=1)
