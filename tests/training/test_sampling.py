"""Query-point sampling: slot contents, coordinates, padding, determinism; each test as a CPU
run draws (candidates found on the host) and as a GPU run draws (random keys, the largest win)."""

from __future__ import annotations

import itertools

import pytest
import torch

from t3fast.data.classes import CAR, FREE, IGNORE, MANMADE, PEDESTRIAN
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.training.sampling import point_voxels, sample_changed_points, sample_query_points, voxel_points

GRID = (12, 10, 6)
N_OCC, N_NEAR, N_FAR = 40, 30, 20


@pytest.fixture(autouse=True, params=["compacted", "sync-free"])
def draws(request):
    if request.param == "compacted":
        yield request.param
        return
    with sync_free():
        yield request.param


def _scene() -> torch.Tensor:
    """Two frames [2, 12, 10, 6]: frame 0 has a car, a wall and ignore voxels; frame 1 three pedestrians."""
    labels = torch.full((2, *GRID), FREE, dtype=torch.uint8)
    labels[0, 2:4, 3:5, 0:2] = CAR  # 8 voxels
    labels[0, 8, :, 0:4] = MANMADE  # 40 voxels -> 48 occupied > N_OCC
    labels[0, 11] = IGNORE
    labels[0, 5, 5, 5] = IGNORE
    labels[1, 6, 5, 2] = labels[1, 0, 0, 0] = labels[1, 11, 9, 5] = PEDESTRIAN
    return labels


def _adjacent_to_occupied(occupied: torch.Tensor) -> torch.Tensor:
    """bool [B, X, Y, Z]: some voxel in the 3x3x3 neighbourhood is occupied (explicit shifts, no pooling)."""
    padded = torch.nn.functional.pad(occupied, (1, 1, 1, 1, 1, 1))
    x, y, z = occupied.shape[1:]
    out = torch.zeros_like(occupied)
    for dx, dy, dz in itertools.product(range(3), repeat=3):
        out |= padded[:, dx : dx + x, dy : dy + y, dz : dz + z]
    return out


def _decode(labels: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Label of the voxel each point falls in, [B, N]."""
    idx = point_voxels(points, GRID)
    b = torch.arange(labels.shape[0]).unsqueeze(1)
    return labels[b, idx[..., 0], idx[..., 1], idx[..., 2]].long()


def _sample(labels: torch.Tensor, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return sample_query_points(labels, N_OCC, N_NEAR, N_FAR, generator=gen)


def test_shapes_coordinates_and_targets() -> None:
    labels = _scene()
    points, targets = _sample(labels)
    assert points.shape == (2, N_OCC + N_NEAR + N_FAR, 3) and points.dtype == torch.float32
    assert targets.shape == (2, N_OCC + N_NEAR + N_FAR) and targets.dtype == torch.int64
    assert points.abs().max() < 1
    # points are exact voxel centres and decode to the target they carry
    idx = point_voxels(points, GRID)
    torch.testing.assert_close(voxel_points(idx, GRID), points)
    real = targets != IGNORE
    assert torch.equal(_decode(labels, points)[real], targets[real])


def test_slots_hold_the_right_voxels() -> None:
    labels = _scene()
    points, targets = _sample(labels)
    occupied = (labels != FREE) & (labels != IGNORE)
    adjacent = _adjacent_to_occupied(occupied)
    idx = point_voxels(points, GRID)
    near_voxel = adjacent[torch.arange(2).unsqueeze(1), idx[..., 0], idx[..., 1], idx[..., 2]]

    occ, near, far = targets[0].split([N_OCC, N_NEAR, N_FAR])
    assert ((occ != FREE) & (occ != IGNORE)).all()  # 48 candidates: the slot is full
    assert (near == FREE).all() and near_voxel[0, N_OCC : N_OCC + N_NEAR].all()
    assert (far == FREE).all() and not near_voxel[0, N_OCC + N_NEAR :].any()
    # no voxel is drawn twice
    flat = idx[0] @ torch.tensor([GRID[1] * GRID[2], GRID[2], 1])
    assert flat.unique().numel() == flat.numel()


def test_few_occupied_are_all_taken_and_padded_with_ignore() -> None:
    labels = _scene()
    points, targets = _sample(labels)
    occ_targets, occ_points = targets[1, :N_OCC], points[1, :N_OCC]
    assert (occ_targets[:3] == PEDESTRIAN).all()
    assert (occ_targets[3:] == IGNORE).all()
    taken = {tuple(v) for v in point_voxels(occ_points[:3], GRID).tolist()}
    assert taken == {(6, 5, 2), (0, 0, 0), (11, 9, 5)}
    # padding points are still valid coordinates for the decoder
    assert (occ_points[3:].abs() < 1).all()


def test_ignore_voxels_are_never_sampled() -> None:
    labels = _scene()
    points, targets = _sample(labels)
    real = targets[0] != IGNORE
    assert (_decode(labels, points)[0][real] != IGNORE).all()
    assert not (point_voxels(points[0][real], GRID)[:, 0] == 11).any()


def test_generator_makes_it_deterministic() -> None:
    labels = _scene()
    p1, t1 = _sample(labels, seed=7)
    p2, t2 = _sample(labels, seed=7)
    p3, _ = _sample(labels, seed=8)
    assert torch.equal(p1, p2) and torch.equal(t1, t2)
    assert not torch.equal(p1, p3)


def test_voxel_points_convention() -> None:
    idx = torch.tensor([[0, 0, 0], [199, 100, 15]])
    pts = voxel_points(idx)  # default Occ3D grid (200, 200, 16): q = (2 i + 1) / N - 1
    torch.testing.assert_close(pts, torch.tensor([[-0.995, -0.995, -0.9375], [0.995, 0.005, 0.9375]]))
    assert torch.equal(point_voxels(pts), idx)
    assert torch.equal(point_voxels(torch.tensor([[-1.0, 1.0, 1.0]])), torch.tensor([[0, 199, 15]]))


def test_empty_batch_and_bad_input() -> None:
    points, targets = sample_query_points(torch.zeros(0, *GRID, dtype=torch.uint8), 2, 3, 4)
    assert points.shape == (0, 9, 3) and targets.shape == (0, 9)
    with pytest.raises(ValueError, match="labels must be"):
        sample_query_points(torch.zeros(GRID, dtype=torch.uint8), 2, 3, 4)


def test_changed_points_are_where_the_frame_changed() -> None:
    before = torch.full((2, 8, 6, 4), FREE, dtype=torch.uint8)
    before[:, :, :, 0] = 11
    before[0, 2, 3, 1] = 4  # a car ...
    labels = before.clone()
    labels[0, 2, 3, 1] = FREE
    labels[0, 3, 3, 1] = 4  # ... one cell on
    labels[0, 5, 5, 2] = IGNORE  # unseen: never a target
    points, targets = sample_changed_points(labels, before, 4)
    assert points.shape == (2, 4, 3) and targets.shape == (2, 4)
    voxels = point_voxels(points, (8, 6, 4))
    got = {(tuple(v.tolist()), int(t)) for v, t in zip(voxels[0], targets[0]) if t != IGNORE}
    assert got == {((2, 3, 1), FREE), ((3, 3, 1), 4)}
    assert (targets[1] == IGNORE).all()  # nothing changed: all padding
    empty = sample_changed_points(labels[:0], before[:0], 4)
    assert empty[0].shape == (0, 4, 3) and empty[1].shape == (0, 4)
    with pytest.raises(ValueError, match="must both be"):
        sample_changed_points(labels, before[:, :4], 4)


def test_a_gpu_run_draws_without_reading_the_device(draws) -> None:
    labels = _scene()
    with SyncCounter() as counter:
        _sample(labels)
        sample_changed_points(labels, labels.roll(1, 1), 10, torch.Generator().manual_seed(0))
    assert (counter.total == 0) == (draws == "sync-free"), counter.by_caller
