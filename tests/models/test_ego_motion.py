"""Planar poses, their extrapolation and moving label volumes between ego frames."""

import math

import pytest
import torch

from t3fast.data.classes import FREE
from t3fast.models.ego_motion import (
    column_queries,
    compose,
    extrapolate_poses,
    frame_queries,
    planar_poses,
    poses_from_displacements,
    relative,
    unwarp_sequence,
    voxel_queries,
    warp_sequence,
    warp_volume,
)


def _matrix(x: float, y: float, yaw: float, z: float = 0.0) -> torch.Tensor:
    m = torch.eye(4, dtype=torch.float64)
    m[0, 0], m[0, 1], m[1, 0], m[1, 1] = math.cos(yaw), -math.sin(yaw), math.sin(yaw), math.cos(yaw)
    m[0, 3], m[1, 3], m[2, 3] = x, y, z
    return m


def test_planar_poses_match_matrices():
    world = torch.stack([_matrix(10, 5, 0.3), _matrix(12, 6, 0.5, z=0.2), _matrix(3, -4, -2.0)])[None]
    poses = planar_poses(world, reference=1)
    assert torch.allclose(poses[0, 1], torch.zeros(3, dtype=torch.float64), atol=1e-12)
    for t in range(3):  # composing the reference's world pose with the relative one gives the world pose
        ref = torch.tensor([12.0, 6.0, 0.5], dtype=torch.float64)
        back = compose(ref, poses[0, t])
        assert torch.allclose(back[:2], world[0, t, :2, 3], atol=1e-9)
        assert math.isclose(math.cos(back[2]), world[0, t, 0, 0].item(), abs_tol=1e-9)


def test_compose_and_relative_are_inverse():
    a, b = torch.randn(5, 3, dtype=torch.float64), torch.randn(5, 3, dtype=torch.float64)
    out = compose(a, relative(a, b))
    assert torch.allclose(out[:, :2], b[:, :2], atol=1e-9)
    assert torch.allclose(torch.cos(out[:, 2] - b[:, 2]), torch.ones(5, dtype=torch.float64))


def test_extrapolation_straight_and_arc():
    straight = torch.tensor([[[-2.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    out = extrapolate_poses(straight, 3)
    assert torch.allclose(out, torch.tensor([[[1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]]]))
    # on a circle of radius 10 m with 0.1 rad per step, the arc continues on the circle
    angles = torch.tensor([-0.2, -0.1, 0.0], dtype=torch.float64)
    past = torch.stack([10 * torch.sin(angles), 10 - 10 * torch.cos(angles), angles], -1)[None]
    fut = extrapolate_poses(past, 4)
    expect = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=torch.float64)
    assert torch.allclose(fut[0, :, 0], 10 * torch.sin(expect), atol=1e-9)
    assert torch.allclose(fut[0, :, 1], 10 - 10 * torch.cos(expect), atol=1e-9)
    assert torch.allclose(fut[0, :, 2], expect, atol=1e-9)
    with pytest.raises(ValueError, match="at least 2 past poses"):
        extrapolate_poses(past[:, :1], 2)


def test_extrapolation_is_the_last_step_composed_again_and_again():
    g = torch.Generator().manual_seed(0)
    past = torch.randn(16, 3, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 4.0, 3.0], dtype=torch.float64)
    step = relative(past[:, -2], past[:, -1])
    pose, want = past[:, -1], []
    for _ in range(6):
        pose = compose(pose, step)
        want.append(pose)
    got = extrapolate_poses(past, 6)
    want = torch.stack(want, 1)
    torch.testing.assert_close(got[..., :2], want[..., :2], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got[..., 2], want[..., 2], rtol=0, atol=1e-12)
    assert got[..., 2].min() >= -math.pi and got[..., 2].max() < math.pi


def test_headings_from_displacements():
    steps = torch.tensor([[[1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0]]])
    poses = poses_from_displacements(steps)
    assert torch.allclose(poses[0, :, :2], steps[0].cumsum(0))
    heading = poses[0, :, 2]
    assert math.isclose(heading[0].item(), math.atan2(1, 2), abs_tol=1e-6)
    assert math.isclose(heading[2].item(), math.pi / 2, abs_tol=1e-6)
    assert heading[3] == heading[2]  # standing still keeps the heading


def _volume(b: int = 1) -> torch.Tensor:
    torch.manual_seed(0)
    return torch.randint(0, 17, (b, 200, 200, 4), dtype=torch.uint8)


def test_warp_identity_and_translation():
    vol = _volume(2)
    assert torch.equal(warp_volume(vol, torch.zeros(2, 3)), vol)
    # the target frame 2 voxels (0.8 m) ahead: its column i is the source's column i + 2
    out = warp_volume(vol, torch.tensor([[0.8, 0.0, 0.0], [0.0, -1.2, 0.0]]))
    assert torch.equal(out[0, :-2], vol[0, 2:])
    assert (out[0, -2:] == FREE).all()  # left the source grid: free
    assert torch.equal(out[1, :, 3:], vol[1, :, :-3])
    assert (out[1, :, :3] == FREE).all()


def test_warp_rotation_by_quarter_turn_is_exact():
    vol = _volume()
    out = warp_volume(vol, torch.tensor([[0.0, 0.0, math.pi / 2]], dtype=torch.float64))
    # a target point (x, y) is the source point (-y, x): target[i, j] = source[199 - j, i]
    assert torch.equal(out[0], torch.rot90(vol[0], -1, (0, 1)))
    assert torch.equal(out[0, 17, 150], vol[0, 199 - 150, 17])


def test_sequence_round_trip_keeps_the_overlap():
    frames = _volume(1).unsqueeze(1).expand(1, 3, -1, -1, -1).clone()
    poses = torch.tensor([[[-3.2, 0.4, -0.05], [-1.6, 0.0, 0.0], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    there_and_back = unwarp_sequence(warp_sequence(frames, poses), poses)
    assert torch.equal(there_and_back[:, 2], frames[:, 2])  # the reference frame itself: untouched
    # the rest agrees wherever a column survived both moves (nearest-column rounding aside)
    kept = there_and_back[:, 1] != FREE
    assert (there_and_back[:, 1][kept] == frames[:, 1][kept]).float().mean() > 0.99
    assert kept.float().mean() > 0.9


@pytest.mark.parametrize("grid", [(200, 200, 16), (7, 5, 3)])
def test_voxel_queries_are_frame_queries_at_those_voxels(grid):
    poses = torch.tensor([[3.0, 0.5, 0.1], [-2.0, 1.0, -0.3]])
    voxels = torch.randint(0, grid[0] * grid[1] * grid[2], (500,), generator=torch.Generator().manual_seed(0))
    assert torch.equal(voxel_queries(poses, grid, voxels), frame_queries(poses, grid)[:, voxels])
    assert voxel_queries(poses, grid, voxels[:0]).shape == (2, 0, 3)


@pytest.mark.parametrize("grid", [(200, 200, 16), (7, 5, 3)])
def test_column_queries_are_frame_queries_at_every_level_of_those_columns(grid):
    poses = torch.tensor([[3.0, 0.5, 0.1], [-2.0, 1.0, -0.3]])
    nx, ny, nz = grid
    columns = torch.randint(0, nx * ny, (2, 40), generator=torch.Generator().manual_seed(1))
    every = frame_queries(poses, grid).view(2, nx * ny, nz, 3)
    expected = torch.stack([every[b, columns[b]] for b in range(2)]).view(2, 40 * nz, 3)
    assert torch.equal(column_queries(poses, grid, columns), expected)
    assert column_queries(poses, grid, columns[:, :0]).shape == (2, 0, 3)
