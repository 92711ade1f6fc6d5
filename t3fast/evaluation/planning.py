"""Planning metrics: L2 error of the planned trajectory and the collision rate.

Horizons 1 s, 2 s, 3 s are future steps 2, 4, 6 (2 Hz); "avg" is the mean of the three.
Two L2 conventions are reported, because published tables mix them:

* ``l2_at``: the L2 distance at the horizon step itself;
* ``l2_mean``: the mean L2 over the steps up to the horizon (ST-P3/OccWorld style).

Collision: the ego footprint (``EGO_LENGTH`` x ``EGO_WIDTH``, heading along its own motion) at
each planned position is tested against the other agents' future boxes (vehicles and humans)
rasterised on the BEV grid (0.4 m cells). Steps where the ground-truth trajectory itself
collides are excluded (annotation noise). ``collision`` at a horizon is the rate over the
included steps up to that horizon.
"""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.data.classes import AGENT_CLASSES, EGO_LENGTH, EGO_WIDTH, GRID_LOWER, GRID_SHAPE, VOXEL_SIZE

HORIZONS = {"1s": 2, "2s": 4, "3s": 6}


def bev_cell_centres(device: torch.device | str = "cpu") -> Tensor:
    """Centres ``[X * Y, 2]`` (x, y in metres) of the BEV grid cells."""
    axes = [GRID_LOWER[a] + VOXEL_SIZE * (torch.arange(GRID_SHAPE[a], device=device) + 0.5) for a in (0, 1)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 2)


def cells_in_boxes(cells: Tensor, boxes: Tensor) -> Tensor:
    """Which cells ``[P, 2]`` lie inside which BEV boxes ``[N, 7]`` (x, y, z, l, w, h, yaw): ``[N, P]``."""
    d = cells[None] - boxes[:, None, :2]
    c, s = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]
    along, across = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
    return (along.abs() <= boxes[:, 3:4] / 2) & (across.abs() <= boxes[:, 4:5] / 2)


def ego_boxes(trajectory: Tensor) -> Tensor:
    """Ego footprints ``[S, 7]`` at the positions ``[S, 2]`` of a trajectory, heading along the
    step's displacement (the previous heading while standing still; 0 at the start)."""
    steps = torch.diff(trajectory, dim=0, prepend=trajectory.new_zeros(1, 2))
    yaw = torch.atan2(steps[:, 1], steps[:, 0])
    moving = steps.norm(dim=1) > 1e-3
    heading, last = torch.zeros_like(yaw), yaw.new_zeros(())
    for i in range(len(yaw)):  # at most 6 steps
        last = yaw[i] if moving[i] else last
        heading[i] = last
    boxes = trajectory.new_zeros(len(trajectory), 7)
    boxes[:, :2], boxes[:, 3], boxes[:, 4], boxes[:, 6] = trajectory, EGO_LENGTH, EGO_WIDTH, heading
    return boxes


def collisions(trajectory: Tensor, boxes: Tensor, valid: Tensor, labels: Tensor, cells: Tensor | None = None) -> Tensor:
    """Per future step, does the ego at ``trajectory [S, 2]`` overlap an agent?

    Args:
        boxes: ``[S, A, 7]`` the agents' boxes at those steps, present-frame coordinates.
        valid: ``[S, A]`` bool; labels: ``[A]`` class ids (only vehicles and humans count).

    Returns:
        bool ``[S]``.
    """
    cells = bev_cell_centres(trajectory.device) if cells is None else cells
    agent = valid & torch.isin(labels, torch.tensor(AGENT_CLASSES, device=labels.device))[None]
    ego = cells_in_boxes(cells, ego_boxes(trajectory))  # [S, P]
    hits = torch.zeros(len(trajectory), dtype=torch.bool, device=trajectory.device)
    for s in range(len(trajectory)):
        if agent[s].any():
            # only the ~50 cells under the ego can collide: test those against the agents
            hits[s] = cells_in_boxes(cells[ego[s]], boxes[s][agent[s]]).any()
    return hits


class PlanningMetrics:
    """Accumulates L2 errors and collisions over an evaluation set."""

    def __init__(self) -> None:
        self.l2: list[Tensor] = []  # [S] per sample
        self.collided: list[Tensor] = []  # [S] bool: planned collides
        self.counted: list[Tensor] = []  # [S] bool: ground truth does not collide
        self._cells: Tensor | None = None

    def update(self, planned: Tensor, truth: Tensor, boxes: Tensor, valid: Tensor, labels: Tensor) -> None:
        """Args: ``planned``/``truth`` trajectories ``[B, S, 2]``; the agents' future boxes
        ``[B, S, A, 7]``, ``valid [B, S, A]``, ``labels [B, A]`` (present-frame coordinates)."""
        if planned.shape != truth.shape or planned.dim() != 3 or planned.shape[-1] != 2:
            raise ValueError(
                f"planned and truth must both be [B, S, 2], got {list(planned.shape)} and {list(truth.shape)}"
            )
        if self._cells is None:
            self._cells = bev_cell_centres(planned.device)
        for b in range(planned.shape[0]):
            self.l2.append((planned[b] - truth[b]).norm(dim=-1).detach().cpu())
            self.collided.append(collisions(planned[b], boxes[b], valid[b], labels[b], self._cells).cpu())
            self.counted.append(~collisions(truth[b], boxes[b], valid[b], labels[b], self._cells).cpu())

    def summary(self) -> dict[str, dict[str, float]]:
        """``{"l2_at", "l2_mean", "collision"}``, each ``{"1s", "2s", "3s", "avg"}`` (metres; rate)."""
        collided, counted = torch.stack(self.collided), torch.stack(self.counted)
        collision = {}
        for name, step in HORIZONS.items():
            n = counted[:, :step].sum()
            collision[name] = float((collided[:, :step] & counted[:, :step]).sum() / n) if n else 0.0
        return l2_summary(torch.stack(self.l2)) | {"collision": with_average(collision)}


def l2_summary(l2: Tensor) -> dict[str, dict[str, float]]:
    """``{"l2_at", "l2_mean"}`` (see the module doc), each ``{"1s", "2s", "3s", "avg"}``, of the
    position errors ``l2`` ``[N, S]`` (metres) of N plans."""
    return {"l2_at": with_average({name: float(l2[:, step - 1].mean()) for name, step in HORIZONS.items()}),
            "l2_mean": with_average({name: float(l2[:, :step].mean()) for name, step in HORIZONS.items()})}


def with_average(by_horizon: dict[str, float]) -> dict[str, float]:
    """``by_horizon`` plus ``"avg"``, the mean over :data:`HORIZONS`."""
    return by_horizon | {"avg": sum(by_horizon[h] for h in HORIZONS) / len(HORIZONS)}
