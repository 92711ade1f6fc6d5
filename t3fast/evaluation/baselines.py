"""Baselines of the world-model evaluation."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.agents.tracker import TRACK_GATE, agent_velocities, frame_agents, move_agents
from t3fast.data.classes import AGENT_CLASSES, FREE, VOXEL_SIZE
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


def track_agents(past_occ: Tensor, past_poses: Tensor, future_poses: Tensor, gate: float = TRACK_GATE,
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
    steps = future_poses.shape[1]
    previous = warp_sequence(past_occ[:, -2:-1], past_poses[:, -2:-1])[:, 0]
    wanted = torch.tensor(classes, dtype=past_occ.dtype, device=past_occ.device)
    k = torch.arange(1, steps + 1, dtype=torch.float64, device=past_occ.device)
    scenes = []
    for n in range(past_occ.shape[0]):
        present = past_occ[n, -1]
        now, before = frame_agents(present, wanted), frame_agents(previous[n], wanted)
        velocity = agent_velocities(now, before, gate / VOXEL_SIZE)
        shift = torch.round(k[:, None, None] * velocity[None]).long()  # [S, n, 2] cells
        scenes.append(move_agents(present, now, shift, FREE))
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
