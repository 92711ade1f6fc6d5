"""Copy&Paste, constant-velocity and ego-motion warp baselines."""

from __future__ import annotations

import torch

from t3fast.data.classes import FREE
from t3fast.evaluation.baselines import constant_velocity, copy_paste, warp_const_vel, warp_present


def test_copy_paste_repeats_the_present_frame():
    past = torch.randint(0, 18, (2, 5, 4, 3, 2), dtype=torch.uint8)
    future = copy_paste(past, steps=6)
    assert future.shape == (2, 6, 4, 3, 2)
    assert all(torch.equal(future[:, k], past[:, -1]) for k in range(6))
    future[0, 0, 0, 0, 0] += 1  # an independent tensor, not a view of the input
    assert not torch.equal(future[:, 0], past[:, -1])


def test_constant_velocity_extrapolates_the_last_displacement():
    past = torch.tensor([[[1.0, 0.0], [2.0, 0.5], [3.0, 1.0], [4.0, -1.0]]])
    plan = constant_velocity(past, steps=6)
    assert plan.shape == (1, 6, 2)
    assert torch.equal(plan.cumsum(1)[0, -1], torch.tensor([24.0, -6.0]))


def _poses_along_x(speeds: list[float]) -> torch.Tensor:
    """Ego -> world poses ``[1, T, 4, 4]`` of an ego driving along +x, ``speeds[t]`` metres per step."""
    poses = torch.eye(4).repeat(len(speeds) + 1, 1, 1)
    poses[1:, 0, 3] = torch.tensor(speeds).cumsum(0)
    return poses[None]


def test_warp_const_vel_moves_the_scene_by_the_extrapolated_motion():
    past = torch.randint(0, 17, (1, 5, 200, 200, 2), dtype=torch.uint8)
    poses = _poses_along_x([9.0, 0.4, 0.4, 0.8])  # last step: 0.8 m = 2 voxels, whatever came before
    future = warp_const_vel(past, poses, steps=3)
    for k in range(3):  # the future frame k + 1 is 2 (k + 1) voxels ahead: static content moves back
        shift = 2 * (k + 1)
        assert torch.equal(future[0, k, :-shift], past[0, -1, shift:])
        assert (future[0, k, -shift:] == FREE).all()


def test_warp_present_with_no_motion_is_copy_paste():
    past = torch.randint(0, 18, (2, 5, 200, 200, 2), dtype=torch.uint8)
    assert torch.equal(warp_present(past, torch.zeros(2, 6, 3)), copy_paste(past, 6))
