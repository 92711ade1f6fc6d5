"""Moving a feature plane by a flow field (a backward lookup, and forward splatting): the flow forecaster's parts.

A flow is backward: ``flow[:, :, i, j]`` says where, in plane cells, the content that ends up
at cell ``(i, j)`` comes from (``(d_i, d_j)``, along dims -2 and -1 of the plane), so the
moved plane is one bilinear lookup per cell (``F.grid_sample``, ``align_corners=False``, the
same cell-centre convention as the decoder's plane lookups) and gradients reach the flow.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

from t3fast.device_constants import made_once


@made_once
def cell_grid(h: int, w: int, device: torch.device, dtype: torch.dtype = torch.float32) -> Tensor:
    """Cell centres ``[h, w, 2]`` in plane cells: ``(i, j)`` (made once per device: read-only)."""
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
    # the four corners (di, dj) = (0, 0), (0, 1), (1, 0), (1, 1) at once, corner after corner
    # along the last dim, so that the sums run in the order of one scatter per corner
    corner = torch.arange(4, device=values.device)  # no host data: on a GPU that would be a copy that waits
    di, dj = corner // 2, corner % 2
    i, j = base[..., :1] + di, base[..., 1:] + dj  # [B, H, W, 4]
    f_i, f_j = frac[..., :1], frac[..., 1:]
    weight = torch.where(di > 0, f_i, 1 - f_i) * torch.where(dj > 0, f_j, 1 - f_j)
    inside = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    index = (i.clamp(0, h - 1) * w + j.clamp(0, w - 1)).permute(0, 3, 1, 2).reshape(b, 1, 4 * h * w)
    weight = (weight * inside).permute(0, 3, 1, 2).reshape(b, 1, 4, h * w).to(values.dtype)
    spread = (values.reshape(b, v, 1, h * w) * weight).reshape(b, v, 4 * h * w)
    out = values.new_zeros(b, v, h * w).scatter_add(2, index.expand(-1, v, -1), spread)
    return out.view(b, v, h, w)
