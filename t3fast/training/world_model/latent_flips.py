"""Mirrored and transposed cached windows: eight times the training windows for free.

A window mirrored across the ego's x or y axis, or with x and y swapped, is as plausible a
window as the original (agents drive either way; the planes' axes are just directions), and
in the ego-aligned latents each of these is an exact rearrangement of the stored planes,
boxes and actions: no encoding. The flow forecaster otherwise fits its few hundred windows
and generalises poorly. The grid is centred on the ego (``GRID_LOWER = -GRID_UPPER`` in x and
y), which is what makes the rearrangement exact.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from t3fast.data.classes import GRID_LOWER, GRID_UPPER
from t3fast.device_constants import device_constant
from t3fast.models.ego_motion import wrap_angle
from t3fast.models.triplane import Triplane
from t3fast.training.world_model.latent_cache import AlignedBatch


def _signs(pair: tuple[float, float], velocity: Tensor) -> Tensor:
    """``pair`` for each (x, y) channel pair of ``velocity`` ``[B, 2k, H, W]``: ``[2k, 1, 1]``."""
    return device_constant(pair * (velocity.shape[1] // 2), velocity.dtype, velocity.device).view(-1, 1, 1)


def flip_aligned(batch: AlignedBatch, flip_x: bool, flip_y: bool, transpose: bool) -> AlignedBatch:
    """``batch`` mirrored in x (x -> -x), then in y, then with x and y swapped (each if asked);
    the agents' velocity field moves with the plane and its components turn with it."""
    if GRID_LOWER[0] != -GRID_UPPER[0] or GRID_LOWER[1] != -GRID_UPPER[1]:
        raise ValueError("flip_aligned needs a grid centred on the ego in x and y")
    xy, xz, yz = batch.planes
    boxes = batch.boxes.clone()
    past, future = batch.past_actions.clone(), batch.future_actions.clone()
    velocity = batch.velocity
    yaw = boxes[..., 6]
    if flip_x:
        xy, xz = xy.flip(-2), None if xz is None else xz.flip(-2)
        velocity = velocity.flip(-2) * _signs((-1.0, 1.0), velocity)
        boxes[..., 0], yaw = -boxes[..., 0], math.pi - yaw
        past[..., 0], future[..., 0] = -past[..., 0], -future[..., 0]
    if flip_y:
        xy, yz = xy.flip(-1), None if yz is None else yz.flip(-2)
        velocity = velocity.flip(-1) * _signs((1.0, -1.0), velocity)
        boxes[..., 1], yaw = -boxes[..., 1], -yaw
        past[..., 1], future[..., 1] = -past[..., 1], -future[..., 1]
    if transpose:
        if xy.shape[-1] != xy.shape[-2]:
            raise ValueError(f"flip_aligned: x and y can only be swapped on a square plane, got {list(xy.shape[-2:])}")
        xy, xz, yz = xy.transpose(-2, -1), yz, xz
        velocity = velocity.transpose(-2, -1).unflatten(1, (-1, 2)).flip(2).flatten(1, 2)  # (x, y) pairs swap
        boxes[..., :2], yaw = boxes[..., :2].flip(-1), math.pi / 2 - yaw
        past, future = past.flip(-1), future.flip(-1)
    boxes[..., 6] = wrap_angle(yaw)
    boxes = boxes.masked_fill(~batch.box_valid[..., None], 0.0)
    return AlignedBatch(Triplane(xy.contiguous(), xz, yz), boxes, batch.box_valid, past, future,
                        velocity.contiguous())


def random_flips(batch: AlignedBatch, generator: torch.Generator | None = None) -> AlignedBatch:
    """``batch`` under one of the eight mirrorings/transpositions, drawn uniformly."""
    return flip_aligned(batch, *draw_flips(generator))


def draw_flips(generator: torch.Generator | None = None) -> tuple[bool, bool, bool]:
    """One of the eight (flip x, flip y, transpose) of :func:`flip_aligned`, drawn uniformly."""
    flip_x, flip_y, transpose = (bool(v) for v in torch.randint(0, 2, (3,), generator=generator, device="cpu"))
    return flip_x, flip_y, transpose
