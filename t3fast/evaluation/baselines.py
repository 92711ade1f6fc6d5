"""Baselines of the world-model evaluation."""

from __future__ import annotations

from torch import Tensor

from t3fast.models.ego_motion import extrapolate_poses, planar_poses, unwarp_sequence


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
