"""Where each present xy-plane cell's content goes: the agents' motion as displacement targets.

Training windows carry the agents' boxes in the present frame at every frame (synthetic data
and Occ3D infos both have them). A cell inside agent ``a``'s box in the present frame holds
part of that agent; at future step ``k`` that part sits at the same place on the agent's box
of frame ``PRESENT + 1 + k``: the cell's forward displacement is that rigid motion. Such a
cell is *moving* when it moves at least ``min_flow`` cells. A cell that no box covers now, or
one of an agent that has not moved (parked cars are most of the agents' cells), is *static*
(displacement 0: in the ego-aligned frame the world stands still). Keeping the two apart
matters: averaged together, the parked cars' zero motion taught a forecaster that agents do
not move. The cells of an agent that leaves the view have no target.
"""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.data.classes import GRID_LOWER, GRID_UPPER
from t3fast.data.sample import PRESENT
from t3fast.device_constants import device_constant
from t3fast.models.ego_motion import rotate


def plane_cell_centres(shape: tuple[int, int], device: torch.device) -> Tensor:
    """Metric ``(x, y)`` of the xy plane's cell centres ``[H, W, 2]`` (present frame)."""
    h, w = shape
    size_x = (GRID_UPPER[0] - GRID_LOWER[0]) / h
    size_y = (GRID_UPPER[1] - GRID_LOWER[1]) / w
    x = GRID_LOWER[0] + size_x * (torch.arange(h, device=device, dtype=torch.float32) + 0.5)
    y = GRID_LOWER[1] + size_y * (torch.arange(w, device=device, dtype=torch.float32) + 0.5)
    return torch.stack(torch.meshgrid(x, y, indexing="ij"), dim=-1)


def _inside(points: Tensor, box: Tensor, margin: float) -> tuple[Tensor, Tensor]:
    """Which of the plane cells' centres ``points`` ``[1, 1, HW, 2]`` lie inside each box
    ``[B, A, 7]`` grown by ``margin``: mask ``[B, A, HW]``, and the cells' coordinates on each
    box ``[B, A, HW, 2]``."""
    local = rotate(points - box[:, :, None, :2], -box[:, :, None, 6])
    return (local.abs() <= box[:, :, None, 3:5] / 2 + margin).all(-1), local


def _covered(points: Tensor, box: Tensor, valid: Tensor, margin: float) -> Tensor:
    """Cells ``[B, HW]`` some valid box (``valid`` ``[B, A]``) of ``box`` ``[B, A, 7]`` covers."""
    return (_inside(points, box, margin)[0] & valid[:, :, None]).any(1)


def agent_cells(boxes: Tensor, box_valid: Tensor, frames: range, shape: tuple[int, int] = (100, 100),
                margin: float = 0.4) -> Tensor:
    """The ``agents`` mask of :func:`agent_motion` for the given ``frames`` of the window only:
    bool ``[B, len(frames), H, W]``, the cells a box covers now or at that frame."""
    points = plane_cell_centres(shape, boxes.device).view(1, 1, -1, 2)
    now = _covered(points, boxes[:, PRESENT], box_valid[:, PRESENT], margin)
    cells = [now | _covered(points, boxes[:, f], box_valid[:, f], margin) for f in frames]
    return torch.stack(cells, 1).view(boxes.shape[0], len(frames), *shape)


def agent_motion(
    boxes: Tensor, box_valid: Tensor, shape: tuple[int, int] = (100, 100), margin: float = 0.4,
    min_flow: float = 0.5,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Forward displacement targets of the present cells, for every future step of windows.

    Args:
        boxes: ``[B, 11, A, 7]`` (x, y, z, l, w, h, yaw) in the present frame.
        box_valid: ``[B, 11, A]``.
        shape: the xy plane's ``(H, W)``.
        margin: metres added to each half-size, so a cell the box only partly covers counts.
        min_flow: plane cells an agent's cell must move to count as moving.

    Returns:
        displacement ``[B, S, 2, H, W]`` in plane cells (``S`` future frames), ``moving`` bool
        ``[B, S, H, W]`` (present cells of an agent seen now and then that moved at least
        ``min_flow``), ``static`` bool ``[B, S, H, W]`` (cells no box covers now, and those of
        agents that did not move: displacement 0), ``agents`` bool ``[B, S, H, W]`` (cells a
        box covers now or at that step), ``covered`` bool ``[B, H, W]`` (cells a box covers now)
        and ``owner`` int64 ``[B, H, W]`` (the box that covers each cell now, ``-1`` none).
    """
    b, t, a, _ = boxes.shape
    h, w = shape
    cell = device_constant(((GRID_UPPER[0] - GRID_LOWER[0]) / h, (GRID_UPPER[1] - GRID_LOWER[1]) / w),
                           torch.float32, boxes.device)
    points = plane_cell_centres(shape, boxes.device).view(1, 1, h * w, 2)  # [1, 1, HW, 2]
    now = boxes[:, PRESENT]  # [B, A, 7]
    in_now, local = _inside(points, now, margin)
    in_now = in_now & box_valid[:, PRESENT, :, None]
    # a cell covered by several boxes takes the last one (boxes of distinct agents rarely overlap)
    owner = torch.where(in_now, torch.arange(a, device=boxes.device).view(1, a, 1), -1).amax(1)  # [B, HW]
    covered_now = owner >= 0
    displacements, moving, static, agents = [], [], [], []
    for frame in range(PRESENT + 1, t):
        future = boxes[:, frame]
        target = future[:, :, None, :2] + rotate(local, future[:, :, None, 6])  # the same point then
        offset = (target - points) / cell  # [B, A, HW, 2] in cells
        picked = offset.gather(1, owner.clamp(min=0).view(b, 1, h * w, 1).expand(-1, 1, -1, 2)).squeeze(1)
        seen = (box_valid[:, frame] & box_valid[:, PRESENT]).gather(1, owner.clamp(min=0)) & covered_now  # [B, HW]
        disp = torch.where(seen[..., None], picked, torch.zeros_like(picked))
        moved = seen & (disp.norm(dim=-1) >= min_flow)
        displacements.append(disp)
        moving.append(moved)
        static.append(~covered_now | (seen & ~moved))
        agents.append(covered_now | _covered(points, future, box_valid[:, frame], margin))
    disp = torch.stack(displacements, 1).view(b, -1, h, w, 2).permute(0, 1, 4, 2, 3)
    return (disp, *(torch.stack(m, 1).view(b, -1, h, w) for m in (moving, static, agents)), covered_now.view(b, h, w),
            owner.view(b, h, w))
