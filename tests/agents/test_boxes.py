"""Agents' boxes fitted to their columns in the past frames, and drawn as the data draws them."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from t3fast.agents.boxes import draw_agent_boxes, fit_agent_boxes, principal_axis
from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, PEDESTRIAN, TRAILER, TRUCK, box_footprint
from t3fast.data.synthetic.render import draw_boxes
from t3fast.data.synthetic.world import ON_GROUND, z_level
from t3fast.models.ego_motion import planar_poses, relative

GRID = (200, 200, 16)


def _empty() -> np.ndarray:
    frame = np.full(GRID, FREE, dtype=np.uint8)
    frame[..., 0] = DRIVEABLE_SURFACE
    return frame


def _scene(boxes_at, poses: torch.Tensor, labels) -> torch.Tensor:
    """Five frames, each in its own ego frame (planar ``poses`` ``[5, 3]`` in the present one),
    with the boxes ``boxes_at(t)`` ``[m, 7]`` (present frame) drawn the way the synthetic data
    draws them."""
    frames = []
    for t in range(poses.shape[0]):
        boxes = torch.as_tensor(boxes_at(t), dtype=torch.float64)
        local = relative(poses[t].double().expand(boxes.shape[0], 3), boxes[:, [0, 1, 6]])
        boxes = boxes.clone()
        boxes[:, 0], boxes[:, 1], boxes[:, 6] = local[:, 0], local[:, 1], local[:, 2]
        frame = _empty()
        draw_boxes(frame, boxes.numpy(), np.asarray(labels))
        frames.append(torch.from_numpy(frame))
    return torch.stack(frames)


def _moving_ego(step: float = 1.3, turn: float = 0.03) -> torch.Tensor:
    """The ego driving and turning: its five planar poses in the present frame."""
    poses, pose = [torch.zeros(3, dtype=torch.float64)], torch.zeros(3, dtype=torch.float64)
    for _ in range(4):  # walk back from the present
        pose = torch.stack([pose[0] - step * math.cos(float(pose[2])), pose[1] - step * math.sin(float(pose[2])),
                            pose[2] - turn])
        poses.append(pose)
    return torch.stack(poses[::-1])


def _yaw_error(a: float, b: float) -> float:
    """Heading difference up to the half turn a box cannot tell."""
    return abs((a - b + math.pi / 2) % math.pi - math.pi / 2)


def test_the_fit_finds_a_moving_car_and_a_walking_pedestrian_to_centimetres():
    car = [10.13, -3.27, 0.3, 4.53, 1.87, 1.6, 0.21]
    walker = [-7.31, 8.57, 0.3, 0.63, 0.71, 1.8, 1.9]
    car_v, walker_v = (1.37, 0.29), (-0.31, 0.57)

    def boxes_at(t: int) -> list[list[float]]:
        back = t - 4
        return [[car[0] + car_v[0] * back, car[1] + car_v[1] * back, *car[2:]],
                [walker[0] + walker_v[0] * back, walker[1] + walker_v[1] * back, *walker[2:]]]

    poses = _moving_ego()
    frames = _scene(boxes_at, poses, [CAR, PEDESTRIAN])
    now, fit = fit_agent_boxes(frames, poses)
    assert sorted(now["cls"].tolist()) == sorted([CAR, PEDESTRIAN]) and fit.drawn.all()
    start = fit_agent_boxes(frames, poses, iters=0)[1]  # the centroids, the last step's displacement
    for truth, velocity, label, reach in ((car, car_v, CAR, 0.03), (walker, walker_v, PEDESTRIAN, 0.08)):
        i = int((fit.label == label).nonzero())
        centre, speed = torch.tensor(truth[:2], dtype=torch.float64), torch.tensor(velocity, dtype=torch.float64)
        assert (fit.centre[i] - centre).norm() < reach and (fit.velocity[i] - speed).norm() < reach
        assert abs(float(fit.length[i]) - truth[3]) < 0.1 and abs(float(fit.width[i]) - truth[4]) < 0.1
        assert fit.bottom[i] == ON_GROUND and fit.top[i] == z_level(truth[5])
    walker_index = int((fit.label == PEDESTRIAN).nonzero())
    # one frame's columns leave the 0.6 m pedestrian anywhere within them; five frames pin it down
    assert (start.centre[walker_index] - torch.tensor(walker[:2])).norm() > 0.1
    car_index = int((fit.label == CAR).nonzero())
    assert _yaw_error(float(fit.yaw[car_index]), car[6]) < 0.05


def test_the_fitted_velocity_of_a_braking_car_is_its_present_one():
    """A car braking at 0.25 m per step^2 moved 1.625 m in its last step and 2 m a step on
    average over the five frames: the fit's velocity is the present one, not the mean."""
    car = [6.4, 2.1, 0.3, 4.6, 1.9, 1.6, 0.12]
    heading = torch.tensor([math.cos(car[6]), math.sin(car[6])], dtype=torch.float64)
    speed_now, decel = 1.5, 0.25

    def boxes_at(t: int) -> list[list[float]]:
        back = t - 4  # steps before the present
        travelled = speed_now * back - 0.5 * decel * back * back  # negative: where it was
        return [[car[0] + float(heading[0]) * travelled, car[1] + float(heading[1]) * travelled, *car[2:]]]

    poses = _moving_ego()
    _, fit = fit_agent_boxes(_scene(boxes_at, poses, [CAR]), poses)
    assert fit.drawn.all()
    present = speed_now * heading + 0.5 * decel * heading  # the last step's displacement
    mean = (torch.tensor(boxes_at(4)[0][:2]) - torch.tensor(boxes_at(0)[0][:2])).double() / 4
    assert (fit.velocity[0] - present).norm() < 0.15 < float((mean - present).norm())


def test_drawn_boxes_are_the_columns_the_data_fills():
    """:func:`draw_agent_boxes` voxelises a box as the synthetic data does (column centres inside
    the footprint and the column under the centre), in a frame at another pose."""
    boxes = torch.tensor([[3.17, -1.91, 0.3, 4.4, 1.9, 1.5, 0.7], [-12.05, 20.3, 0.3, 0.5, 0.5, 1.7, -2.0]],
                         dtype=torch.float64)
    pose = torch.tensor([1.7, -0.4, 0.25], dtype=torch.float64)
    expected = _scene(lambda t: boxes, pose[None], [CAR, PEDESTRIAN])[0]
    volume = torch.from_numpy(_empty())
    tops = torch.tensor([z_level(1.5), z_level(1.7)])
    draw_agent_boxes(volume, boxes[:, :2], boxes[:, 6], boxes[:, 3], boxes[:, 4], torch.full((2,), ON_GROUND), tops,
                     torch.tensor([CAR, PEDESTRIAN]), pose)
    assert torch.equal(volume, expected)


def test_overlapping_boxes_are_drawn_in_order_level_by_level_and_off_grid_ones_are_clipped():
    """The later box wins where two cover a voxel, only on the levels it spans; a box half off
    the grid draws its part on the grid; the result is box by box with the data's footprint."""
    boxes = torch.tensor([[0.3, 0.2, 5.0, 2.2, 0.4], [1.1, -0.3, 3.0, 1.8, -0.5], [39.1, -39.6, 4.0, 2.0, 1.0],
                          [-55.0, 0.0, 4.0, 2.0, 0.0]], dtype=torch.float64)
    bottom, top = torch.tensor([1, 0, 1, 1]), torch.tensor([6, 3, 3, 3])
    labels = torch.tensor([TRUCK, CAR, CAR, CAR])
    volume = torch.from_numpy(_empty())
    expected = volume.clone()
    for i in range(4):  # box by box, as the synthetic data draws them
        footprint = box_footprint(*boxes[i].tolist(), GRID[:2])
        if footprint is not None:
            rows, cols, inside = footprint
            levels = (torch.arange(GRID[2]) >= bottom[i]) & (torch.arange(GRID[2]) < top[i])
            block = expected[rows, cols]
            block[torch.from_numpy(inside)[:, :, None] & levels] = int(labels[i])
    draw_agent_boxes(volume, boxes[:, :2], boxes[:, 4], boxes[:, 2], boxes[:, 3], bottom, top, labels,
                     torch.zeros(3, dtype=torch.float64))
    assert torch.equal(volume, expected)
    assert (volume == TRUCK).any() and (volume[:, :, 3:6] == TRUCK).sum() > (volume[:, :, 1:3] == TRUCK).sum()
    assert (volume[190:, :10] == CAR).any()  # the corner box, clipped


def test_agents_the_fit_cannot_explain_move_as_voxels():
    """A truck with its trailer is one component of two classes, an agent seen in one frame has
    no motion to fit, and a frame without agents has nothing to fit."""
    poses = torch.zeros(5, 3, dtype=torch.float64)
    rig = [[0.0, 0.0, 0.3, 6.0, 2.4, 3.0, 0.0], [-7.0, 0.0, 0.3, 8.0, 2.4, 3.0, 0.0]]
    frames = _scene(lambda t: rig, poses, [TRUCK, TRAILER])
    frames[:4, 150:160, 20:24, 1:3] = FREE
    frames[4, 150:160, 20:24, 1:3] = CAR  # appears in the present only
    now, fit = fit_agent_boxes(frames, poses)
    assert now["cls"].shape[0] == 2 and not fit.drawn.any()
    now, fit = fit_agent_boxes(torch.from_numpy(_empty())[None].repeat(5, 1, 1, 1), poses)
    assert now["cls"].shape[0] == 0 and fit.centre.shape == (0, 2) and fit.drawn.shape == (0,)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match=r"frames must be \[T, X, Y, Z\] and poses \[T, 3\]"):
        fit_agent_boxes(torch.zeros(5, 200, 200, dtype=torch.uint8), torch.zeros(5, 3))
    with pytest.raises(ValueError, match=r"frames must be \[T, X, Y, Z\] and poses \[T, 3\]"):
        fit_agent_boxes(torch.zeros(5, 200, 200, 16, dtype=torch.uint8), torch.zeros(4, 3))


def test_the_boxes_of_several_windows_at_once_are_each_window_s_alone():
    """With fixed slots (a GPU forecast), the windows' boxes are fitted in one call: each
    window's are those it gets alone, and alone with slots they are the counted agents' boxes."""
    from dataclasses import fields

    from t3fast.data.sample import PRESENT
    from t3fast.data.synthetic import SyntheticDriving

    windows = SyntheticDriving("val", 2, 20, stride=9)
    frames = torch.stack([windows[i].occ[: PRESENT + 1] for i in range(2)])
    poses = planar_poses(torch.stack([windows[i].ego_poses[: PRESENT + 1] for i in range(2)]), PRESENT)
    now, fit = fit_agent_boxes(frames, poses, slots=64)
    assert fit.centre.shape == (2, 64, 2) and fit.track.shape == (2, 64, PRESENT + 1, 2)
    for b in range(2):
        alone_now, alone = fit_agent_boxes(frames[b], poses[b], slots=64)
        counted_now, counted = fit_agent_boxes(frames[b], poses[b])
        n = counted_now["cls"].shape[0]
        assert 5 < n < 64 and torch.equal(now["ids"][b], alone_now["ids"])
        for f in fields(fit):
            got, want, exact = getattr(fit, f.name), getattr(alone, f.name), getattr(counted, f.name)
            if got is None:
                continue
            torch.testing.assert_close(got[b], want, rtol=0, atol=0, equal_nan=True, msg=f.name)
            torch.testing.assert_close(want[:n], exact, rtol=1e-9, atol=1e-9, equal_nan=True, msg=f.name)
        assert fit.drawn[b, :n].any() and not fit.drawn[b, n:].any()


def test_principal_axis_is_the_larger_eigenvector_in_closed_form():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1000, 2, 7, generator=g, dtype=torch.float64)
    cov = x @ x.mT
    axis = principal_axis(cov)
    values, vectors = torch.linalg.eigh(cov)
    torch.testing.assert_close(axis.norm(dim=-1), torch.ones(1000, dtype=torch.float64))
    torch.testing.assert_close((cov @ axis[..., None])[..., 0], values[..., 1:] * axis)  # cov v = lambda_max v
    torch.testing.assert_close((axis * vectors[..., 1]).sum(-1).abs(), torch.ones(1000, dtype=torch.float64))
    assert (axis[..., 0] >= 0).all()  # one sign on every device, whatever the solver would pick
    # isotropic and axis-aligned spreads
    spreads = torch.stack([torch.eye(2), torch.diag(torch.tensor([4.0, 1.0])), torch.diag(torch.tensor([1.0, 4.0]))])
    torch.testing.assert_close(principal_axis(spreads), torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
