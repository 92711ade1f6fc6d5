"""The fused operators of t3fast.

Each has a pure-PyTorch twin with the same signature in :mod:`t3fast.ops.reference`. The
compiled kernels are also reachable as ``torch.ops.t3fast.<name>`` once this module is
imported. Where the extension is not built (or was built against another torch), the ops run
through the references instead, with the same argument checks, and importing this module warns
once; :func:`build_info` says why.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from typing import Any

from torch import Tensor

from t3fast.ops import _checks, reference
from t3fast.ops._checks import checked_grid
from t3fast.ops._extension import _C, BUILD_HINT, UNAVAILABLE_REASON

__all__ = ["axis_pool", "bev_components", "box_fit", "build_info", "delta_fuse", "draw_boxes", "group_norm_silu",
           "label_conv3d", "matching_costs", "reference", "triplane_decode"]

if _C is not None:
    from t3fast.ops._registration import ops
else:
    ops = None
    warnings.warn(
        f"t3fast's compiled operators are not available ({UNAVAILABLE_REASON}); the ops run through "
        f"their pure-PyTorch references, which are slower and take more memory; {BUILD_HINT}.",
        RuntimeWarning,
        stacklevel=1,  # this module, whose import is what falls back
    )


def build_info() -> dict[str, Any]:
    """How the compiled extension was built.

    Returns:
        ``{"compiled": True, "cpu": True, "cuda": bool, "cuda_version": int (major*1000 +
        minor*10, -1 without CUDA), "torch_version": str, "openmp": bool}``; without a usable
        extension ``{"compiled": False, "reason": str (why, and how to build it), "cpu": False,
        "cuda": False, "cuda_version": -1, "torch_version": None, "openmp": False}``.
    """
    if _C is None:
        return {
            "compiled": False,
            "reason": f"{UNAVAILABLE_REASON}; {BUILD_HINT}",
            "cpu": False,
            "cuda": False,
            "cuda_version": -1,
            "torch_version": None,
            "openmp": False,
        }
    return {"compiled": True, **_C.build_info()}


def triplane_decode(
    xy: Tensor,
    xz: Tensor,
    yz: Tensor,
    weights: Sequence[Tensor],
    biases: Sequence[Tensor],
    *,
    grid: Sequence[int] | None = None,
    points: Tensor | None = None,
    pe_freqs: int = 6,
    argmax: bool = False,
    live: Tensor | None = None,
) -> Tensor:
    """Fused triplane query -> sum -> positional encoding -> MLP decode.

    For each query point (x, y, z) in [-1, 1]^3 the three planes are looked up bilinearly
    (``F.grid_sample`` with ``align_corners=False``, ``padding_mode="border"``; xy at (x, y)
    with x along dim -2, xz at (x, z), yz at (y, z)), the three C-vectors are summed, the
    encoding ``[sin(2^0 x), sin(2^0 y), sin(2^0 z), cos(2^0 x), cos(2^0 y), cos(2^0 z),
    sin(2^1 x), ...]`` (6 * pe_freqs values) is appended, and the MLP (ReLU between layers,
    none after the last) maps the features to class logits.

    Args:
        xy: ``[B, C, X', Y']`` plane.
        xz: ``[B, C, X', Z']`` plane.
        yz: ``[B, C, Y', Z']`` plane.
        weights: per layer ``[out_i, in_i]`` (``nn.Linear`` layout), ``in_0 = C + 6 * pe_freqs``.
        biases: per layer ``[out_i]``.
        grid: ``(X, Y, Z)``: query every voxel centre ``(2 i + 1) / N - 1`` of that grid; an
            output larger than the device's memory is refused with a ``ValueError``.
        points: ``[B, N, 3]`` query coordinates (x, y, z); they receive no gradient.
        pe_freqs: number of encoding frequencies F.
        argmax: return the first-maximum class as uint8 instead of logits (no logits
            tensor is ever allocated; needs 1 to 256 classes). Exactly what
            ``torch.argmax`` returns on the logits: NaN counts as the maximum, so a row
            with a NaN logit gets its first NaN's class.
        live: int64 ``[B]`` on the planes' device (``points`` and ``argmax`` only): decode
            only the first ``live[b]`` points of batch element ``b`` (clamped to ``[0, N]``)
            and give the others label 0. The counts stay on the device, so a fixed-size
            buffer of points, filled to a data-dependent length, costs what its filled part
            costs without a host read.

    Returns:
        logits ``[B, X, Y, Z, K]`` (grid) or ``[B, N, K]`` (points); with ``argmax`` uint8
        labels ``[B, X, Y, Z]`` or ``[B, N]``.

    Exactly one of ``grid`` and ``points`` must be given. Differentiable with respect to
    the planes, weights and biases (not the points). float32/float64 on CPU, also
    float16/bfloat16 on CUDA.
    """
    weights, biases = list(weights), list(biases)
    if grid is not None and weights:
        grid = checked_grid(grid, xy, weights[-1].shape[0], argmax)
    if ops is None:
        _checks.check_triplane_decode(xy, xz, yz, weights, biases, points, grid, pe_freqs, argmax, live)
        # as the kernels: the points receive no gradient
        points = None if points is None else points.detach()
        return reference.triplane_decode(xy, xz, yz, weights, biases, grid=grid, points=points,
                                         pe_freqs=pe_freqs, argmax=argmax, live=live)
    return ops.triplane_decode.default(
        xy,
        xz,
        yz,
        weights,
        biases,
        points,
        grid,
        int(pe_freqs),
        bool(argmax),
        live,
    )


def axis_pool(volume: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Three axis means of a volume in one read.

    Args:
        volume: ``[B, C, X, Y, Z]``.

    Returns:
        ``xy [B, C, X, Y]`` (mean over Z), ``xz [B, C, X, Z]`` (mean over Y),
        ``yz [B, C, Y, Z]`` (mean over X).
    """
    if ops is None:
        _checks.check_axis_pool(volume)
        return reference.axis_pool(volume)
    return ops.axis_pool.default(volume)


def delta_fuse(delta: Tensor, prev: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``next = delta + conv1x1(prev) + bias`` in one pass.

    Args:
        delta: ``[B, C, H, W]`` predicted change.
        prev: ``[B, C_in, H, W]`` previous plane.
        weight: ``[C, C_in]`` 1x1 convolution weight.
        bias: ``[C]`` or None.

    Returns:
        ``[B, C, H, W]``.
    """
    if ops is None:
        _checks.check_delta_fuse(delta, prev, weight, bias)
        return reference.delta_fuse(delta, prev, weight, bias)
    return ops.delta_fuse.default(delta, prev, weight, bias)


def matching_costs(present: Tensor, previous: Tensor, radius: int) -> Tensor:
    """How well each cell of ``present`` matches the cells of ``previous`` around it (a local
    cost volume): ``out[:, n]`` is minus the channel-mean absolute difference to ``previous``
    shifted by the n-th ``(d_i, d_j)`` of ``[-radius, radius]^2`` (row-major; replicate padding
    at the edges). The best match sits where the content came from: a local view of motion.

    One pass over the planes: no ``[B, C, H, 2r + 1, W]`` difference tensor in memory, as the
    reference (:func:`t3fast.ops.reference.matching_costs`) needs for each row of shifts.

    Args:
        present: ``[B, C, H, W]``, at least one channel; float32/float64 (on CUDA also
            float16/bfloat16, accumulated in float32).
        previous: ``[B, C, H, W]``, as ``present``.
        radius: the largest shift, 0 to 64.

    Returns:
        ``[B, (2 radius + 1)^2, H, W]`` in the inputs' dtype. Differentiable with respect to
        both planes (the subgradient 0 where two values tie, as ``abs``).
    """
    if ops is None:
        _checks.check_matching_costs(present, previous, radius)
        return reference.matching_costs(present, previous, radius)
    return ops.matching_costs.default(present, previous, radius)


def group_norm_silu(input: Tensor, weight: Tensor, bias: Tensor, groups: int, eps: float = 1e-5,
                    residual: Tensor | None = None) -> Tensor:
    """``silu(group_norm(input, groups, weight, bias, eps) + residual)``: a convolution block's
    normalisation, residual add and activation in one op.

    Two reads of ``input`` (the groups' sums, then the output) and one write, where
    ``group_norm``, the add and ``silu`` run one after another read and write the activation
    four to seven times; the backward reads it twice more. Under autocast the op computes in
    float32 (as ``group_norm`` does under CUDA's autocast).

    Args:
        input: ``[B, C, *]``; float32/float64 (on CUDA also float16/bfloat16, accumulated in
            float32).
        weight, bias: ``[C]``, the dtype of ``input``.
        groups: a divisor of ``C``; group ``g`` is channels ``g C / groups`` to
            ``(g + 1) C / groups - 1``.
        eps: added to the variance (biased, as ``group_norm``'s).
        residual: ``[B, C, *]`` as ``input``, added after the affine transform; or None.

    Returns:
        ``[B, C, *]`` in the dtype of ``input``. Differentiable with respect to ``input``,
        ``weight``, ``bias`` and ``residual`` (once).
    """
    if ops is None:
        _checks.check_group_norm_silu(input, weight, bias, groups, eps, residual)
        return reference.group_norm_silu(input, weight, bias, groups, eps, residual)
    return ops.group_norm_silu.default(input, weight, bias, groups, eps, residual)[0]


def label_conv3d(labels: Tensor, table: Tensor) -> Tensor:
    """A 3 x 3 x 3 convolution (zero padding 1) of class-embedded labels, as 27 table lookups
    per voxel: ``out[b, :, x, y, z] = sum over dx, dy, dz in {-1, 0, 1} of
    table[9 (dx + 1) + 3 (dy + 1) + dz + 1, labels[b, x + dx, y + dy, z + dz], :]``, taps
    outside the volume contributing nothing.

    ``conv3d(embedding(labels).permute(0, 4, 1, 2, 3), weight, padding=1)`` is this op with
    ``table = einsum("ceijk,ke->ijkc", weight, embedding.weight)`` (reshaped to ``[27, K, C]``):
    ``C`` adds per tap instead of ``E * C`` multiply-adds, and no embedded volume in memory.

    Args:
        labels: ``[B, X, Y, Z]`` uint8, int32 or int64 class ids in ``[0, K)``; the CPU kernel
            refuses others, the CUDA kernel does not check them (that would synchronise with
            the host) and they then contribute nothing.
        table: ``[27, K, C]`` float32/float64 (on CUDA also float16/bfloat16).

    Returns:
        ``[B, C, X, Y, Z]`` in the table's dtype. Differentiable with respect to the table.
    """
    if ops is None:
        _checks.check_label_conv3d(labels, table)
        return reference.label_conv3d(labels, table)
    return ops.label_conv3d.default(labels, table)


def bev_components(mask: Tensor) -> tuple[Tensor, Tensor]:
    """The 8-connected components of bird's-eye-view masks, without a host synchronisation.

    Args:
        mask: ``[B, X, Y]`` bool.

    Returns:
        labels int64 ``[B, X, Y]``: 0 off the mask, 1..n on it, the components numbered in the
        row-major order of their last cell; and n, the number of components, int64 ``[B]`` (a
        tensor on the mask's device: reading it is the caller's choice).
    """
    if ops is None:
        _checks.check_bev_components(mask)
        return reference.bev_components(mask)
    return ops.bev_components.default(mask)


def draw_boxes(volume: Tensor, boxes: Tensor, levels: Tensor, labels: Tensor, lower: Sequence[float],
               voxel_size: float, reach: int) -> Tensor:
    """Boxes drawn into label volumes, in order: a later box wins where boxes overlap.

    Box ``m`` of volume ``b`` fills the levels ``levels[m, 0] <= z < levels[m, 1]`` of every
    column within ``reach`` columns (along each axis) of its centre column whose centre lies
    inside its footprint, and of its centre column (a small agent never vanishes), with
    ``labels[m]``. A column's centre is ``lower + voxel_size * (index + 0.5)``.

    Args:
        volume: uint8 ``[B, X, Y, Z]`` labels to draw into (not modified).
        boxes: float64 ``[B, M, 6]``: centre x, y, the cosine and sine of the heading, half the
            length, half the width (metres, in the volume's frame).
        levels: int64 ``[M, 2]``: bottom (inclusive) and top (exclusive) level of each box; or
            ``[B, M, 2]``, each volume's boxes' own (several windows' boxes in one call).
        labels: uint8 ``[M]``: each box's class; ``[B, M]`` with ``[B, M, 2]`` levels.
        lower: the grid's lower x and y (metres); voxel_size: metres per column.
        reach: how many columns from the centre column are tested.

    Returns:
        uint8 ``[B, X, Y, Z]``: ``volume`` with the boxes drawn.
    """
    if ops is None:
        _checks.check_draw_boxes(volume, boxes, levels, labels, lower, voxel_size, reach)
        return reference.draw_boxes(volume, boxes, levels, labels, lower, voxel_size, reach)
    return ops.draw_boxes.default(volume, boxes, levels, labels, [float(v) for v in lower], float(voxel_size),
                                  int(reach))


def box_fit(ids: Tensor, track: Tensor, centroid: Tensor, poses: Tensor, start: Tensor, reach: Tensor,
            lower: Sequence[float], voxel_size: float, window: int, near: int, iters: int, lr: float,
            softness: Sequence[float], accel_prior: float) -> tuple[Tensor, Tensor]:
    """Agents' boxes fitted to their grid columns in every frame of a window, on the device,
    without a host synchronisation.

    Agent ``a`` of window ``b`` samples, in every frame ``t`` where it was found
    (``track[b, a, t] >= 0``), the columns within ``reach[b, a]`` cells (Euclidean, capped at
    ``window``) of its rounded centroid and within ``near`` columns of one it owns (component
    map value ``track + 1``); each sample's centre is taken into the present frame with the
    frame's pose (column centres at ``lower + voxel_size * (index + 0.5)``). Its box (centre,
    velocity, acceleration, yaw, length, width) is fitted by ``iters`` Adam steps (learning
    rate ``lr``) on the summed logistic loss of a soft inside/outside (the signed distance to
    the footprint's edge over a width narrowing from ``softness[0]`` to ``softness[1]``
    metres) against ownership, over the window's samples, plus ``accel_prior`` times the
    acceleration's square, over the window's fitted agents
    (:func:`t3fast.ops.reference.fit_loss`). Computed in float32 around each agent's starting
    centre.

    Args:
        ids: int64 ``[B, T, X, Y]``: each frame's component map (0 off the agents, else 1 + component).
        track: int64 ``[B, n, T]``: each agent's component in every frame, -1 where not found.
        centroid: float64 ``[B, n, T, 2]``: that component's column centroid (cells; read where found).
        poses: float64 ``[B, T, 3]``: each frame's planar pose (x, y, yaw) in the present frame.
        start: float64 ``[B, n, 7]``: the boxes to start from: centre x, y (metres, present
            frame), velocity per step, yaw, log length, log width.
        reach: float64 ``[B, n]``: cells around the centroid sampled; <= 0 (or NaN): not fitted.

    Returns:
        boxes float64 ``[B, n, 7]`` as ``start`` (the velocity the present one of the constant
        acceleration fitted with them; an agent not fitted keeps its start) and each one's
        footprint IoU with its columns over the frames, float64 ``[B, n]`` (0 if not fitted).
    """
    args = (ids, track, centroid, poses, start, reach, [float(v) for v in lower], float(voxel_size), int(window),
            int(near), int(iters), float(lr), [float(v) for v in softness], float(accel_prior))
    if ops is None:
        _checks.check_box_fit(*args)
        return reference.box_fit(*args)
    return ops.box_fit.default(*args)
