"""The route command a driving planner is told: turn right, turn left or go straight.

Derived as the nuScenes planners' info files derive it (VAD / UniAD ``gt_ego_fut_cmd``, a
one-hot of these three in this order): from where the ego is 3 s ahead, in the present ego
frame (x forward, y left). A lateral offset of at least :data:`TURN_OFFSET` metres to the right
is a right turn, to the left a left turn, anything less is straight on. The command thus looks
3 s into the ego's own future, as a route planner or navigation system does: results that use
it say so. Mirroring a window left-right swaps left and right.
"""

from __future__ import annotations

import torch
from torch import Tensor

RIGHT, LEFT, STRAIGHT = 0, 1, 2
COMMANDS = ("turn right", "turn left", "go straight")  # index = command, as in gt_ego_fut_cmd
TURN_OFFSET = 2.0  # metres sideways 3 s ahead that make a turn


def route_command(future_actions: Tensor) -> Tensor:
    """The command of windows from their future ego displacements ``[..., 6, 2]`` (present
    frame, metres per step) -> int64 ``[...]``: :data:`RIGHT`, :data:`LEFT` or :data:`STRAIGHT`."""
    if future_actions.dim() < 2 or future_actions.shape[-1] != 2:
        raise ValueError(f"route_command: future_actions must be [..., steps, 2], got {list(future_actions.shape)}")
    lateral = future_actions[..., 1].sum(-1)
    straight = torch.full(lateral.shape, STRAIGHT, dtype=torch.int64, device=future_actions.device)
    return torch.where(lateral >= TURN_OFFSET, LEFT, torch.where(lateral <= -TURN_OFFSET, RIGHT, straight))


def mirror_command(command: Tensor) -> Tensor:
    """The command of a window mirrored left-right (y -> -y): left and right swap."""
    return torch.where(command == LEFT, RIGHT, torch.where(command == RIGHT, LEFT, command))
