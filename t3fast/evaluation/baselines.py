"""Baselines of the world-model evaluation."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from t3fast.data.classes import AGENT_CLASSES, FREE, NUM_CLASSES, VOXEL_SIZE
from t3fast.models.ego_motion import extrapolate_poses, planar_poses, unwarp_sequence, warp_sequence


def copy_paste(past_occ: Tensor, steps: int = 6) -> Tensor:
    """Copy&Paste: the present frame repeated. ``[B, T, X, Y, Z] -> [B, steps, X, Y, Z]``."""
    return past_occ[:, -1:].expand(-1, steps, *past_occ.shape[2:]).clone()


def constant_velocity(past_actions: Tensor, steps: int = 6) -> Tensor:
    """Constant-velocity ego motion: the last displacement repeated (actions are all in the
    present frame, so no rotation is needed). ``[B, T, 2] -> [B, steps, 2]`` displacements;
    ``.cumsum(1)`` gives the trajectory."""
    return past_actions[:, -1:].expand(-1, steps, 2).clone()


def warp_present(past_occ: Tensor, future_poses: Tensor) -> Tensor:
    """The present frame ``past_occ[:, -1]`` moved into each future ego frame, given the future
    planar poses ``[B, S, 3]`` in the present frame (nearest voxel column; what leaves the
    present grid becomes free). Returns ``[B, S, X, Y, Z]``."""
    return unwarp_sequence(copy_paste(past_occ, future_poses.shape[1]), future_poses)


def warp_const_vel(past_occ: Tensor, ego_poses: Tensor, steps: int = 6) -> Tensor:
    """``warp_present`` with poses extrapolated at constant velocity and yaw rate from the past
    poses (past information only). ``past_occ`` ``[B, T, X, Y, Z]`` and ``ego_poses``
    ``[B, >=T, 4, 4]`` (ego -> world) share their first T frames; the present is frame T-1."""
    t = past_occ.shape[1]
    past = planar_poses(ego_poses[:, :t], t - 1)
    return warp_present(past_occ, extrapolate_poses(past, steps))


def bev_components(mask: Tensor) -> tuple[Tensor, int]:
    """8-connected components of a BEV mask ``[X, Y]`` (bool): labels int64 ``[X, Y]``, 0 off the
    mask and 1..n on it, and n. Label propagation: every cell takes the largest label of its
    3x3 neighbourhood (max-pooling) and then the label its label points at (pointer jumping,
    so a component of diameter d converges in about log d rounds rather than d)."""
    nx, ny = mask.shape
    if not bool(mask.any()):
        return torch.zeros(nx, ny, dtype=torch.long, device=mask.device), 0
    keep = mask.float()
    # labels are 1 + the flat index of a cell of the same component (exact in float32 below 2^24)
    labels = (torch.arange(1, nx * ny + 1, dtype=torch.float32, device=mask.device).view(nx, ny) * keep)
    while True:
        pooled = F.max_pool2d(labels[None, None], 3, stride=1, padding=1)[0, 0] * keep
        flat = pooled.flatten()
        jumped = torch.maximum(flat, flat[(flat.long() - 1).clamp(min=0)] * keep.flatten()).view(nx, ny)
        if torch.equal(jumped, labels):
            break
        labels = jumped
    _, inverse = torch.unique(labels.long(), return_inverse=True)  # 0 (off the mask) stays 0
    return inverse, int(inverse.max())


def _agents(frame: Tensor, classes: Tensor) -> dict[str, Tensor]:
    """The agents of a frame ``[X, Y, Z]``: their voxels (``ijz`` ``[V, 3]``, ``label`` ``[V]``,
    ``component`` ``[V]`` 0-based) and, per connected BEV component of the columns holding an
    agent voxel, its majority class ``cls`` ``[n]`` and column centroid ``centroid`` ``[n, 2]`` (cells)."""
    is_agent = torch.isin(frame, classes)
    ids, n = bev_components(is_agent.any(-1))
    ijz = is_agent.nonzero()
    label = frame[is_agent].long()
    component = ids[ijz[:, 0], ijz[:, 1]] - 1
    votes = torch.zeros(n, NUM_CLASSES, dtype=torch.long, device=frame.device)
    votes.index_put_((component, label), torch.ones_like(label), accumulate=True)
    cols = (ids > 0).nonzero()
    col_id = ids[cols[:, 0], cols[:, 1]] - 1
    size = torch.bincount(col_id, minlength=n).double()
    centroid = torch.stack([torch.bincount(col_id, cols[:, a].double(), minlength=n) for a in (0, 1)], -1)
    return dict(ijz=ijz, label=label, component=component, cls=votes.argmax(1),
                centroid=centroid / size.clamp(min=1)[:, None], mask=is_agent)


def agent_velocities(present: dict[str, Tensor], previous: dict[str, Tensor], gate_cells: float) -> Tensor:
    """Per present component, its velocity in cells per step ``[n, 2]``: the displacement of its
    centroid from the nearest previous component of its class (both in the present frame);
    0 without one within ``gate_cells``."""
    n = present["cls"].shape[0]
    velocity = torch.zeros(n, 2, dtype=torch.float64, device=present["cls"].device)
    if n == 0 or previous["cls"].shape[0] == 0:
        return velocity
    diff = present["centroid"][:, None] - previous["centroid"][None]  # [n, m, 2]
    dist = diff.norm(dim=-1).masked_fill(present["cls"][:, None] != previous["cls"][None], math.inf)
    nearest, match = dist.min(1)
    found = nearest <= gate_cells
    velocity[found] = diff[found, match[found]]
    return velocity


def track_agents(past_occ: Tensor, past_poses: Tensor, future_poses: Tensor, gate: float = 4.0,
                 classes: tuple[int, ...] = AGENT_CLASSES) -> Tensor:
    """Classical tracker: every agent moved along its velocity, then the scene into each future
    ego frame.

    The previous frame ``past_occ[:, -2]`` is moved into the present frame with the past poses
    (ego compensation); in both, the columns holding an agent voxel (``classes``: vehicles and
    humans) form 8-connected BEV components, each with its majority class. A present component
    takes the velocity (centroid displacement per 0.5 s step) from the previous component of
    its class with the nearest centroid, if that is within ``gate`` metres, else 0. Future step
    k: the agents' voxels of the present frame become free and each component's agent voxels
    (whole columns, heights kept) are pasted k velocities away (nearest voxel; what leaves the
    grid is dropped); that scene is moved into future frame k like :func:`warp_present`.

    Args:
        past_occ: ``[B, T, X, Y, Z]`` (T >= 2), the present last.
        past_poses: planar poses ``[B, T, 3]`` of those frames in the present frame.
        future_poses: planar poses ``[B, S, 3]`` of the future frames in the present frame.
    Returns:
        ``[B, S, X, Y, Z]``, same dtype as ``past_occ``.
    """
    b, _, nx, ny, nz = past_occ.shape
    steps = future_poses.shape[1]
    previous = warp_sequence(past_occ[:, -2:-1], past_poses[:, -2:-1])[:, 0]
    wanted = torch.tensor(classes, dtype=past_occ.dtype, device=past_occ.device)
    k = torch.arange(1, steps + 1, dtype=torch.float64, device=past_occ.device)
    scenes = []
    for n in range(b):
        present = past_occ[n, -1]
        now, before = _agents(present, wanted), _agents(previous[n], wanted)
        velocity = agent_velocities(now, before, gate / VOXEL_SIZE)
        shift = torch.round(k[:, None, None] * velocity[None]).long()  # [S, n, 2] cells
        base = present.masked_fill(now["mask"], FREE)
        frames = base.expand(steps, nx, ny, nz).clone()
        if now["ijz"].shape[0]:
            ijz = now["ijz"]
            moved = ijz[None, :, :2] + shift[:, now["component"]]  # [S, V, 2]
            inside = (moved[..., 0] >= 0) & (moved[..., 0] < nx) & (moved[..., 1] >= 0) & (moved[..., 1] < ny)
            step = torch.arange(steps, device=ijz.device)[:, None].expand_as(inside)
            z = ijz[None, :, 2].expand_as(inside)
            frames[step[inside], moved[..., 0][inside], moved[..., 1][inside], z[inside]] = (
                now["label"].to(frames.dtype).expand(steps, -1)[inside])
        scenes.append(frames)
    return unwarp_sequence(torch.stack(scenes), future_poses)


def track_const_vel(past_occ: Tensor, ego_poses: Tensor, steps: int = 6) -> Tensor:
    """:func:`track_agents` with the future ego poses extrapolated at constant velocity and yaw
    rate from the past poses, as :func:`warp_const_vel` (past information only)."""
    t = past_occ.shape[1]
    past = planar_poses(ego_poses[:, :t], t - 1)
    return track_agents(past_occ, past, extrapolate_poses(past, steps))


def track_gt_ego(past_occ: Tensor, ego_poses: Tensor, steps: int = 6) -> Tensor:
    """:func:`track_agents` with the TRUE future ego poses ``ego_poses[:, T:T + steps]`` (uses
    ground-truth ego motion)."""
    t = past_occ.shape[1]
    poses = planar_poses(ego_poses[:, : t + steps], t - 1)
    return track_agents(past_occ, poses[:, :t], poses[:, t:])
