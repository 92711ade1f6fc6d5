"""Where each xy-plane cell's content comes from: the agents' motion as flow targets.

Training windows carry the agents' boxes in the present frame at every frame (synthetic data
and Occ3D infos both have them). For future step ``k`` a cell inside agent ``a``'s box at
frame ``PRESENT + 1 + k`` holds what was at the same place on that agent's box in the present
frame: its backward flow is that rigid motion taken back. Such a cell is *moving* when that
flow is at least ``min_flow`` cells. A cell that no box covers, now or then, or one of an agent
that has not moved (parked cars are most of the agents' cells), is *static* (flow 0: in the
ego-aligned frame the world stands still). Keeping the two apart matters: averaged together,
the parked cars' zero flow taught a forecaster that agents do not move. Cells an agent
uncovers, and agents that were not in view in the present frame, have no flow target (their
content is new, which Delta must produce).
"""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.data.classes import GRID_LOWER, GRID_UPPER
from t3fast.data.sample import PRESENT


def plane_cell_centres(shape: tuple[int, int], device: torch.device) -> Tensor:
    """Metric ``(x, y)`` of the xy plane's cell centres ``[H, W, 2]`` (present frame)."""
    h, w = shape
    size_x = (GRID_UPPER[0] - GRID_LOWER[0]) / h
    size_y = (GRID_UPPER[1] - GRID_LOWER[1]) / w
    x = GRID_LOWER[0] + size_x * (torch.arange(h, device=device, dtype=torch.float32) + 0.5)
    y = GRID_LOWER[1] + size_y * (torch.arange(w, device=device, dtype=torch.float32) + 0.5)
    return torch.stack(torch.meshgrid(x, y, indexing="ij"), dim=-1)


def _rotate(v: Tensor, yaw: Tensor) -> Tensor:
    c, s = yaw.cos(), yaw.sin()
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], dim=-1)


def agent_flow(
    boxes: Tensor, box_valid: Tensor, shape: tuple[int, int] = (100, 100), margin: float = 0.4,
    min_flow: float = 0.5,
) -> tuple[Tensor, Tensor, Tensor]:
    """Backward flow targets of the future steps of windows.

    Args:
        boxes: ``[B, 11, A, 7]`` (x, y, z, l, w, h, yaw) in the present frame.
        box_valid: ``[B, 11, A]``.
        shape: the xy plane's ``(H, W)``.
        margin: metres added to each half-size, so a cell the box only partly covers counts.
        min_flow: plane cells an agent's cell must move to count as moving.

    Returns:
        flow ``[B, S, 2, H, W]`` in plane cells (``S`` future frames), ``moving`` bool
        ``[B, S, H, W]`` (cells inside the box of an agent seen now and then that moved at
        least ``min_flow``: flow target from its motion), ``static`` bool ``[B, S, H, W]``
        (cells no box covers now or then, and those of agents that did not move: flow 0).
    """
    b, t, a, _ = boxes.shape
    h, w = shape
    cell = torch.tensor([(GRID_UPPER[0] - GRID_LOWER[0]) / h, (GRID_UPPER[1] - GRID_LOWER[1]) / w],
                        device=boxes.device)
    points = plane_cell_centres(shape, boxes.device).view(1, 1, h * w, 2)  # [1, 1, HW, 2]
    now = boxes[:, PRESENT]  # [B, A, 7]

    def inside(box: Tensor) -> tuple[Tensor, Tensor]:
        """Cells inside each box ``[B, A, 7]``: mask ``[B, A, HW]`` and local coordinates."""
        local = _rotate(points - box[:, :, None, :2], -box[:, :, None, 6])
        half = box[:, :, None, 3:5] / 2 + margin
        return (local.abs() <= half).all(-1), local

    in_now, _ = inside(now)
    in_now = in_now & box_valid[:, PRESENT, :, None]
    flows, moving, static = [], [], []
    for frame in range(PRESENT + 1, t):
        future = boxes[:, frame]
        in_then, local = inside(future)
        seen = box_valid[:, PRESENT] & box_valid[:, frame]  # [B, A]
        hit = in_then & seen[:, :, None]
        source = now[:, :, None, :2] + _rotate(local, now[:, :, None, 6])  # the same point on the box now
        offset = (source - points) / cell  # [B, A, HW, 2] in cells
        # a cell covered by several boxes takes the last one (boxes of distinct agents rarely overlap)
        owner = torch.where(hit, torch.arange(a, device=boxes.device).view(1, a, 1), -1).amax(1)  # [B, HW]
        picked = offset.gather(1, owner.clamp(min=0).view(b, 1, h * w, 1).expand(-1, 1, -1, 2)).squeeze(1)
        covered = owner >= 0
        flow = torch.where(covered[..., None], picked, torch.zeros_like(picked))
        moved = covered & (flow.norm(dim=-1) >= min_flow)
        flows.append(flow)
        moving.append(moved)
        any_then = (in_then & box_valid[:, frame, :, None]).any(1)
        static.append(~(any_then | in_now.any(1)) | (covered & ~moved))
    flow = torch.stack(flows, 1).view(b, -1, h, w, 2).permute(0, 1, 4, 2, 3)
    return flow, torch.stack(moving, 1).view(b, -1, h, w), torch.stack(static, 1).view(b, -1, h, w)
