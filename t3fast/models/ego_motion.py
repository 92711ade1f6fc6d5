"""Ego motion as geometry: planar poses, their extrapolation, and moving label volumes
between ego frames.

Every Occ3D frame is in its own ego frame, so between two frames the whole static scene
moves by the ego's motion. The world model does not learn that: it brings its history into
the present frame with the past poses, forecasts there (static content stays still), and
moves each forecast into the future frame's own coordinates with the pose it plans or is
given. Poses here are planar, ``(x, y, yaw)`` of a frame's ego in a reference frame (metres,
radians, counter-clockwise from +x): the grid is 16 voxels high and driving is planar, so a
height or pitch change between frames is ignored.

Resampling is nearest-voxel: each voxel column of the target frame takes the column of the
source frame that contains its centre, the whole column at once (heights do not change);
columns whose centre falls outside the source grid get ``fill`` (free: unobserved). Grids
are centred on the ego in x and y with 0.4 m voxels, as Occ3D's (any X, Y: the tests use small
ones).
"""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.data.classes import FREE, VOXEL_SIZE
from t3fast.device_constants import made_once


def planar_poses(ego_poses: Tensor, reference: int) -> Tensor:
    """Planar pose of every frame in frame ``reference``'s ego coordinates.

    Args:
        ego_poses: ego -> world ``[B, T, 4, 4]``.
    Returns:
        ``[B, T, 3]`` (x, y, yaw); frame ``reference`` is (0, 0, 0).
    """
    # inv_ex: inv would check the factorisation on the host, a wait (and no CUDA graph) on a GPU;
    # the inputs' check has already refused non-finite poses
    rel = torch.linalg.inv_ex(ego_poses[:, reference : reference + 1].double()).inverse @ ego_poses.double()
    yaw = torch.atan2(rel[..., 1, 0], rel[..., 0, 0])
    return torch.stack([rel[..., 0, 3], rel[..., 1, 3], yaw], dim=-1).to(ego_poses.dtype)


def rotate(v: Tensor, angle: Tensor) -> Tensor:
    """Vectors ``[..., 2]`` turned counter-clockwise by ``angle`` ``[...]``."""
    c, s = angle.cos(), angle.sin()
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """Points ``[..., 2]`` (x, y, given in the frame at planar ``pose`` ``[..., 3]``) expressed in
    the pose's reference frame, ``[..., 2]``."""
    c, s = torch.cos(pose[..., 2]), torch.sin(pose[..., 2])
    x = pose[..., 0] + c * points[..., 0] - s * points[..., 1]
    y = pose[..., 1] + s * points[..., 0] + c * points[..., 1]
    return torch.stack([x, y], dim=-1)


def compose(a: Tensor, b: Tensor) -> Tensor:
    """Pose ``b`` (given in frame ``a``) expressed in ``a``'s reference frame: ``a * b``, ``[..., 3]``."""
    return torch.cat([transform_points(a, b), wrap_angle(a[..., 2:] + b[..., 2:])], dim=-1)


def relative(a: Tensor, b: Tensor) -> Tensor:
    """Pose ``b`` in frame ``a`` (both given in one reference frame): ``a^-1 * b``, ``[..., 3]``."""
    c, s = torch.cos(a[..., 2]), torch.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return torch.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], dim=-1)


def wrap_angle(angle: Tensor) -> Tensor:
    """Angles wrapped to ``[-pi, pi)``."""
    return torch.remainder(angle + torch.pi, 2 * torch.pi) - torch.pi


def extrapolate_poses(past: Tensor, steps: int) -> Tensor:
    """Constant velocity and yaw rate: the last step's motion, in the ego's own frame, repeated.

    Args:
        past: planar poses ``[B, T, 3]`` (T >= 2) in the present frame, the present last.
    Returns:
        ``[B, steps, 3]`` future poses in the present frame (an arc of constant curvature).
    """
    if past.shape[1] < 2:
        raise ValueError(f"extrapolate_poses needs at least 2 past poses, got {past.shape[1]}")
    step = relative(past[:, -2], past[:, -1])
    present = past[:, -1]
    # in closed form: step k + 1 moves by the step's translation turned to heading k
    k = torch.arange(steps, device=past.device, dtype=past.dtype)
    heading = present[:, 2:] + k * step[:, 2:]  # [B, steps], unwrapped
    xy = present[:, None, :2] + rotate(step[:, None, :2], heading).cumsum(1)
    return torch.cat([xy, wrap_angle(heading + step[:, 2:]).unsqueeze(-1)], dim=-1)


def poses_from_displacements(displacements: Tensor) -> Tensor:
    """Future poses from displacements ``[B, S, 2]`` (present frame; the ego at the origin):
    positions are their cumulative sum, each heading is the direction of travel around that
    step (the mean of the incoming and outgoing displacements; the last step's own direction
    at the end). A displacement shorter than 5 cm keeps the previous heading, starting from
    the present heading (0). Returns ``[B, S, 3]``."""
    b, s = displacements.shape[:2]
    xy = displacements.cumsum(1)
    nxt = torch.cat([displacements[:, 1:], displacements[:, -1:]], dim=1)
    direction = displacements + nxt
    heading = torch.atan2(direction[..., 1], direction[..., 0])
    moving = direction.norm(dim=-1) > 0.05
    prev = torch.zeros(b, dtype=displacements.dtype, device=displacements.device)
    out = []
    for k in range(s):
        prev = torch.where(moving[:, k], heading[:, k], prev)
        out.append(prev)
    return torch.cat([xy, torch.stack(out, dim=1).unsqueeze(-1)], dim=-1)


def displacements_from_poses(poses: Tensor) -> Tensor:
    """Per-step displacements ``[B, S, 2]`` of future poses ``[B, S, 3]`` in the present frame
    (the ego at the origin): the inverse of :func:`poses_from_displacements`' positions."""
    xy = poses[..., :2]
    return torch.cat([xy[:, :1], xy[:, 1:] - xy[:, :-1]], dim=1)


@made_once
def _column_centres(nx: int, ny: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """A frame's voxel column centres ``[X * Y, 2]`` (x, y in metres) in that frame."""
    xs = VOXEL_SIZE * (torch.arange(nx, device=device, dtype=dtype) + 0.5 - nx / 2)
    ys = VOXEL_SIZE * (torch.arange(ny, device=device, dtype=dtype) + 0.5 - ny / 2)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    return torch.stack([gx.flatten(), gy.flatten()], -1)


def _columns_in(target_in_source: Tensor, grid: tuple[int, int]) -> Tensor:
    """Centres of a target frame's voxel columns in the source frame, ``[B, X * Y, 2]`` (x, y)."""
    cols = _column_centres(grid[0], grid[1], target_in_source.device, target_in_source.dtype)
    return transform_points(target_in_source[:, None, :], cols[None])


def column_index(target_in_source: Tensor, grid: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """For each voxel column of a target frame whose pose in the source frame is
    ``target_in_source`` ``[B, 3]``: the flat index of the source column containing its centre
    and whether it lies inside the source grid. Returns ``([B, X * Y] int64, [B, X * Y] bool)``."""
    nx, ny = grid
    src = _columns_in(target_in_source, grid)
    i = torch.floor(src[..., 0] / VOXEL_SIZE + nx / 2).long()
    j = torch.floor(src[..., 1] / VOXEL_SIZE + ny / 2).long()
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    return (i.clamp(0, nx - 1) * ny + j.clamp(0, ny - 1)), inside


def warp_volume(volume: Tensor, target_in_source: Tensor, fill: int = FREE) -> Tensor:
    """A volume ``[B, X, Y, Z]`` (or ``[B, X, Y, Z, ...]``) of the source frame resampled into
    a target frame whose pose in the source frame is ``target_in_source`` ``[B, 3]``
    (nearest column; outside the source grid: ``fill``)."""
    b, nx, ny = volume.shape[:3]
    index, inside = column_index(target_in_source, (nx, ny))
    flat = volume.reshape(b, nx * ny, -1)
    out = torch.gather(flat, 1, index[..., None].expand(-1, -1, flat.shape[-1]))
    out = torch.where(inside[..., None], out, fill)
    return out.view(volume.shape)


def warp_sequence(frames: Tensor, poses: Tensor, fill: int = FREE) -> Tensor:
    """Frames ``[B, T, X, Y, Z]``, each in its own ego frame with planar pose ``poses``
    ``[B, T, 3]`` in a common reference frame, all resampled into that reference frame."""
    ref_in_frame = relative(poses, torch.zeros_like(poses))  # the reference frame seen from each frame
    out = warp_volume(frames.flatten(0, 1), ref_in_frame.flatten(0, 1), fill)
    return out.view(frames.shape)


def unwarp_sequence(frames: Tensor, poses: Tensor, fill: int = FREE) -> Tensor:
    """The inverse of :func:`warp_sequence`: frames ``[B, T, X, Y, Z]`` in the reference frame
    resampled into each frame's own ego frame (pose ``poses`` ``[B, T, 3]`` in the reference)."""
    return warp_volume(frames.flatten(0, 1), poses.flatten(0, 1), fill).view(frames.shape)


def frame_queries(poses: Tensor, grid: tuple[int, int, int]) -> Tensor:
    """Decoder query points of every voxel centre of frames whose planar poses in the
    forecasting frame are ``poses`` ``[B, 3]``: ``[B, X * Y * Z, 3]`` in that frame's normalised
    coordinates (z fastest, so the result reshapes to ``[B, X, Y, Z]``). Columns beyond the
    forecasting frame's grid take its outermost column: the forecast continues its edge there
    (a road running out of the grid goes on) instead of declaring what it cannot see free."""
    x, y, z = _query_axes(poses, grid)
    return _column_points(x, y, z)


def column_queries(poses: Tensor, grid: tuple[int, int, int], columns: Tensor) -> Tensor:
    """:func:`frame_queries` of every level of the flat columns ``columns`` ``[B, M]`` (indices
    into the X * Y columns of each frame): ``[B, M * Z, 3]``, equal to
    ``frame_queries(poses, grid).view(B, X * Y, Z, 3)[b, columns[b]]`` flattened, without building
    the other columns' points."""
    x, y, z = _query_axes(poses, grid)
    return _column_points(x.gather(1, columns), y.gather(1, columns), z)


def _column_points(x: Tensor, y: Tensor, z: Tensor) -> Tensor:
    """Columns at ``x``, ``y`` ``[B, M]`` times levels at ``z`` ``[Z]``: ``[B, M * Z, 3]``, z fastest."""
    b, m, nz = *x.shape, z.shape[0]
    return torch.stack([x[..., None].expand(b, m, nz), y[..., None].expand(b, m, nz), z.expand(b, m, nz)],
                       -1).view(b, m * nz, 3)


def voxel_queries(poses: Tensor, grid: tuple[int, int, int], voxels: Tensor) -> Tensor:
    """:func:`frame_queries` of the flat voxel indices ``voxels`` only (``[N]``: the same for
    every frame; ``[B, N]``: per frame): ``[B, N, 3]``, equal to
    ``frame_queries(poses, grid)[:, voxels]`` without building the other voxels' points."""
    x, y, z = _query_axes(poses, grid)
    column, level = voxels // grid[2], voxels % grid[2]
    column = column.expand(poses.shape[0], -1)
    return torch.stack([x.gather(1, column), y.gather(1, column), z[level].expand(poses.shape[0], -1)], -1)


def _query_axes(poses: Tensor, grid: tuple[int, int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """The normalised x and y ``[B, X * Y]`` of each column of frames at ``poses`` ``[B, 3]``
    (clamped to the forecasting frame's outermost voxel centres) and the levels' z ``[Z]``."""
    nx, ny, nz = grid
    src = _columns_in(poses, (nx, ny))  # metres in the forecasting frame
    # clamped to the outermost voxel centres, so a column beyond the grid decodes exactly as the
    # last one inside (planes and positional encoding alike)
    x = (src[..., 0] / (VOXEL_SIZE * nx / 2)).clamp(-1 + 1 / nx, 1 - 1 / nx)
    y = (src[..., 1] / (VOXEL_SIZE * ny / 2)).clamp(-1 + 1 / ny, 1 - 1 / ny)
    z = (2 * torch.arange(nz, device=poses.device, dtype=poses.dtype) + 1) / nz - 1
    return x, y, z
