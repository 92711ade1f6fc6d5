"""Copy&Paste, constant-velocity, ego-motion warp and tracker baselines."""

from __future__ import annotations

import torch

from t3fast import ops
from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, MANMADE, PEDESTRIAN, TRUCK
from t3fast.evaluation.baselines import (
    constant_velocity,
    copy_paste,
    track_const_vel,
    track_gt_ego,
    warp_const_vel,
    warp_present,
)


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


# the tracker: a small grid (40 x 40 columns, 4 high) with flat road and boxes standing on it

X, Y, Z = 40, 40, 4


def _scene(boxes: list[tuple[int, int, int, int, int]]) -> torch.Tensor:
    """Road at z 0, and boxes ``(class, x0, y0, length_x, height)`` two cells wide in y from z 1."""
    frame = torch.full((X, Y, Z), FREE, dtype=torch.uint8)
    frame[:, :, 0] = DRIVEABLE_SURFACE
    for cls, x0, y0, length, height in boxes:
        frame[max(x0, 0) : max(x0 + length, 0), y0 : y0 + 2, 1 : 1 + height] = cls
    return frame


def _static_poses(frames: int = 11) -> torch.Tensor:
    return torch.eye(4).repeat(1, frames, 1, 1)


def _track(frames: list[torch.Tensor], poses: torch.Tensor | None = None, steps: int = 3) -> torch.Tensor:
    past = torch.stack(frames)[None]
    return track_gt_ego(past, _static_poses() if poses is None else poses, steps)[0]


def test_tracker_moves_a_car_by_its_velocity():
    frames = [_scene([(CAR, 4 + 2 * t, 10, 3, 2)]) for t in range(5)]  # 2 cells per step along x
    future = _track(frames)
    for k in range(1, 4):
        assert torch.equal(future[k - 1], _scene([(CAR, 12 + 2 * k, 10, 3, 2)])), k


def test_tracker_compensates_the_ego_motion():
    # the ego drives 1 cell (0.4 m) per step along x, the car 3 cells: in each ego frame it gains 2 cells
    poses = _static_poses()
    poses[0, :, 0, 3] = 0.4 * torch.arange(11.0)
    frames = [_scene([(CAR, 4 + 2 * t, 10, 3, 2)]) for t in range(5)]
    past = torch.stack(frames)[None]
    for forecast in (track_gt_ego(past, poses, 3)[0], track_const_vel(past, poses[:, :5], 3)[0]):
        for k in range(1, 4):
            expected = _scene([(CAR, 12 + 2 * k, 10, 3, 2)])
            expected[X - k :] = FREE  # beyond the present grid: not seen
            assert torch.equal(forecast[k - 1], expected), k


def test_tracker_with_nothing_moving_is_copy_paste():
    frame = _scene([(CAR, 5, 5, 4, 2), (PEDESTRIAN, 20, 30, 1, 3), (MANMADE, 30, 10, 5, 3)])
    past = frame.expand(5, X, Y, Z)[None]
    assert torch.equal(track_gt_ego(past, _static_poses(), 6), copy_paste(past, 6))
    assert torch.equal(track_const_vel(past, _static_poses(5), 6), copy_paste(past, 6))


def test_tracker_associates_within_a_class():
    # the car moves +4 cells per step along x, the truck -2; the truck's previous position is nearer
    # to the present car than the car's own previous one, so only the class keeps them apart
    def frame(t: int) -> torch.Tensor:
        return _scene([(CAR, 3 + 4 * t, 10, 3, 2), (TRUCK, 26 - 2 * t, 13, 3, 3)])

    assert ops.bev_components(torch.isin(frame(4), torch.tensor([CAR, TRUCK], dtype=torch.uint8)).any(-1)[None])[1] == 2
    future = _track([frame(t) for t in range(5)])
    for k in range(1, 4):
        assert torch.equal(future[k - 1], frame(4 + k)), k


def test_an_unmatched_car_stays():
    # car A moves 2 cells per step; car B appears in the present frame, far from any previous car
    frames = [_scene([(CAR, 5 + 2 * t, 5, 3, 2)]) for t in range(4)]
    frames.append(_scene([(CAR, 13, 5, 3, 2), (CAR, 30, 30, 3, 2)]))
    future = _track(frames)
    for k in range(1, 4):
        assert torch.equal(future[k - 1], _scene([(CAR, 13 + 2 * k, 5, 3, 2), (CAR, 30, 30, 3, 2)])), k
