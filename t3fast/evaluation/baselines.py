"""Baselines of the world-model evaluation."""

from __future__ import annotations

from torch import Tensor


def copy_paste(past_occ: Tensor, steps: int = 6) -> Tensor:
    """Copy&Paste: the present frame repeated. ``[B, T, X, Y, Z] -> [B, steps, X, Y, Z]``."""
    return past_occ[:, -1:].expand(-1, steps, *past_occ.shape[2:]).clone()


def constant_velocity(past_actions: Tensor, steps: int = 6) -> Tensor:
    """Constant-velocity ego motion: the last displacement repeated (actions are all in the
    present frame, so no rotation is needed). ``[B, T, 2] -> [B, steps, 2]`` displacements;
    ``.cumsum(1)`` gives the trajectory."""
    return past_actions[:, -1:].expand(-1, steps, 2).clone()
