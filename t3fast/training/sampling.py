"""Query-point sampling for training the triplane decoder on a subset of voxels.

Points are voxel centres in the decoder's normalised coordinates: cell ``i`` of ``N``
along an axis sits at ``q = (2 i + 1) / N - 1``, in ``(-1, 1)``, ordered ``(x, y, z)``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from t3fast.data.classes import FREE, GRID_SHAPE, IGNORE
from t3fast.device_constants import device_constant
from t3fast.host_syncs import reads_host

__all__ = ["near_surface_free", "point_voxels", "sample_changed_points", "sample_query_points", "voxel_points"]


def voxel_points(indices: torch.Tensor, grid: tuple[int, int, int] = GRID_SHAPE) -> torch.Tensor:
    """Voxel indices ``[..., 3]`` (x, y, z) -> centre coordinates ``[..., 3]`` float32 in ``(-1, 1)``."""
    sizes = device_constant(grid, torch.float32, indices.device)
    return (2.0 * indices.float() + 1.0) / sizes - 1.0


def point_voxels(points: torch.Tensor, grid: tuple[int, int, int] = GRID_SHAPE) -> torch.Tensor:
    """Coordinates ``[..., 3]`` in ``[-1, 1]`` -> index ``[..., 3]`` int64 of the voxel containing each point.

    Inverse of :func:`voxel_points`; points on the border are clamped into the grid.
    """
    sizes = device_constant(grid, torch.float32, points.device)
    idx = torch.floor((points.float() + 1.0) * 0.5 * sizes).long()
    return torch.minimum(idx.clamp(min=0), sizes.long() - 1)


def near_surface_free(occupied: torch.Tensor, free: torch.Tensor, radius: int = 1) -> torch.Tensor:
    """Free voxels with an occupied voxel within ``radius`` cells (Chebyshev distance).

    Args:
        occupied, free: bool ``[B, X, Y, Z]``.
        radius: half-size of the cubic neighbourhood.

    Returns:
        bool ``[B, X, Y, Z]``.
    """
    # a 3D max-pool of the occupied mask is its dilation by a (2r+1)^3 cube
    dilated = F.max_pool3d(occupied.unsqueeze(1).float(), 2 * radius + 1, stride=1, padding=radius).squeeze(1)
    return free & (dilated > 0)


def _pick(candidates: torch.Tensor, count: int, values: torch.Tensor, ignore_index: int,
          generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``count`` flat indices of candidates (bool ``[V]``) drawn uniformly without replacement,
    and their ``values``; when fewer candidates are left, the slot is padded with voxel 0 and
    target ``ignore_index``. On the CPU the candidates are found on the host; elsewhere each
    voxel draws a random key and the ``count`` largest win (:func:`~t3fast.host_syncs.reads_host`:
    nothing waits for the device)."""
    if reads_host(candidates.device):
        idx = candidates.nonzero().squeeze(1)
        if idx.numel() > count:
            idx = idx[torch.randperm(idx.numel(), generator=generator, device=idx.device)[:count]]
        targets = values[idx]
    else:
        keys = torch.rand(candidates.shape, generator=generator, device=candidates.device)
        top, idx = keys.masked_fill_(~candidates, -1.0).topk(min(count, keys.numel()))
        picked = top >= 0
        idx, targets = torch.where(picked, idx, 0), torch.where(picked, values[idx], ignore_index)
    pad = count - idx.numel()  # too few candidates (or voxels)
    return torch.cat([idx, idx.new_zeros(pad)]), torch.cat([targets, targets.new_full((pad,), ignore_index)])


def sample_query_points(
    labels: torch.Tensor,
    num_occupied: int,
    num_near_free: int,
    num_far_free: int,
    generator: torch.Generator | None = None,
    free_class: int = FREE,
    ignore_index: int = IGNORE,
    near_radius: int = 1,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample training query points: occupied voxels, free voxels near surfaces, far free voxels.

    Every sample gets the same ``N = num_occupied + num_near_free + num_far_free`` points,
    in three consecutive slots:

    * occupied (label neither free nor ignore): all of them if they fit, else a random subset;
    * near free: free voxels within ``near_radius`` cells of an occupied voxel, random subset;
    * far free: the other free voxels, random subset.

    A slot with too few candidates is padded with points at voxel ``(0, 0, 0)`` whose target
    is ``ignore_index``, so losses skip them. Ignore voxels are never sampled.

    Args:
        labels: ``[B, X, Y, Z]`` integer labels (uint8 or int64).
        num_occupied, num_near_free, num_far_free: slot sizes.
        generator: optional ``torch.Generator`` (on ``labels``' device) for reproducible draws.
        free_class: label of empty space.
        ignore_index: label never sampled, also the target of padding points.
        near_radius: neighbourhood half-size defining "near a surface".

    Returns:
        ``points`` ``[B, N, 3]`` float32 voxel centres (x, y, z) in ``(-1, 1)`` and ``targets``
        ``[B, N]`` int64.
    """
    if labels.dim() != 4:
        raise ValueError(f"sample_query_points: labels must be [B, X, Y, Z], got {tuple(labels.shape)}")
    if min(num_occupied, num_near_free, num_far_free) < 0:
        raise ValueError("sample_query_points: slot sizes must be >= 0")
    grid = tuple(labels.shape[1:])
    total = num_occupied + num_near_free + num_far_free
    if labels.shape[0] == 0:
        return labels.new_zeros((0, total, 3), dtype=torch.float32), labels.new_zeros((0, total), dtype=torch.long)
    free = labels == free_class
    occupied = ~free & (labels != ignore_index)
    near = near_surface_free(occupied, free, near_radius)
    far = free & ~near
    slots = ((occupied, num_occupied), (near, num_near_free), (far, num_far_free))
    flat_idx, targets = [], []
    for b in range(labels.shape[0]):
        values = labels[b].reshape(-1).long()
        picks = [_pick(m[b].reshape(-1), n, values, ignore_index, generator) for m, n in slots]
        flat_idx.append(torch.cat([p[0] for p in picks]))
        targets.append(torch.cat([p[1] for p in picks]))
    return _flat_points(torch.stack(flat_idx), grid), torch.stack(targets)


def _flat_points(flat: torch.Tensor, grid: tuple[int, int, int]) -> torch.Tensor:
    """Flat voxel indices ``[B, N]`` -> centre coordinates ``[B, N, 3]``."""
    ny, nz = grid[1], grid[2]
    return voxel_points(torch.stack([flat // (ny * nz), (flat // nz) % ny, flat % nz], dim=-1), grid)


def sample_changed_points(
    labels: torch.Tensor,
    before: torch.Tensor,
    count: int,
    generator: torch.Generator | None = None,
    ignore_index: int = IGNORE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Query points where ``labels`` differ from ``before`` (both ``[B, X, Y, Z]``, same frame):
    what appeared, vanished or changed class, e.g. agents that moved. A forecaster that copies
    its input is right almost everywhere, so these few voxels carry the signal of motion.

    Returns ``points`` ``[B, count, 3]`` and ``targets`` ``[B, count]`` (the ``labels`` there),
    padded like :func:`sample_query_points`; ignore voxels (of either) are never sampled."""
    if labels.shape != before.shape or labels.dim() != 4:
        raise ValueError(f"sample_changed_points: labels {tuple(labels.shape)} and before {tuple(before.shape)} "
                         "must both be [B, X, Y, Z]")
    if count < 0:
        raise ValueError("sample_changed_points: count must be >= 0")
    changed = (labels != before) & (labels != ignore_index) & (before != ignore_index)
    flat_idx, targets = [], []
    for b in range(labels.shape[0]):
        idx, target = _pick(changed[b].reshape(-1), count, labels[b].reshape(-1).long(), ignore_index, generator)
        flat_idx.append(idx)
        targets.append(target)
    if not flat_idx:
        return labels.new_zeros((0, count, 3), dtype=torch.float32), labels.new_zeros((0, count), dtype=torch.long)
    return _flat_points(torch.stack(flat_idx), tuple(labels.shape[1:])), torch.stack(targets)
