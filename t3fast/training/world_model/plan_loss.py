"""The route planner's inputs and loss on cached ego-aligned windows.

The loss is the mean distance (metres) between the planned and the true future positions over
the six steps. Each batch is mirrored left-right at random (planes, actions and so the route
command, derived from the mirrored future: :func:`~t3fast.data.route.route_command`); the other
rearrangements the forecaster trains on (x mirrored, x and y swapped) would put the road behind
or beside the ego, not ahead. The command is dropped from a share of the windows so the planner
also plans without one.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from t3fast.data.route import route_command
from t3fast.data.sample import PRESENT
from t3fast.training.step_draws import toss, uniform
from t3fast.training.world_model.latent_cache import AlignedBatch
from t3fast.training.world_model.latent_flips import flip_aligned


@dataclass
class PlanBatch:
    """What the route planner reads (``inputs``: present and previous xy planes
    ``[B, C, H, W]``, past displacements ``[B, 4, 2]``, commands ``[B]``, -1 where dropped) and
    the true future displacements ``[B, 6, 2]``."""

    inputs: tuple[Tensor, Tensor, Tensor, Tensor]
    future_actions: Tensor


def plan_batch(batch: AlignedBatch, command_dropout: float, generator: torch.Generator | None = None,
               mirror: bool | None = None) -> PlanBatch:
    """The route planner's training inputs from cached windows (see the module doc), mirrored
    where ``mirror`` (None: a coin toss)."""
    if toss(generator) if mirror is None else mirror:
        batch = flip_aligned(batch, False, True, False)
    xy = batch.planes.xy
    command = drop_commands(route_command(batch.future_actions), command_dropout, generator)
    return PlanBatch((xy[:, PRESENT], xy[:, PRESENT - 1], batch.past_actions, command), batch.future_actions)


def drop_commands(command: Tensor, share: float, generator: torch.Generator | None = None) -> Tensor:
    """Route commands ``[B]`` with each replaced by -1 (none) with probability ``share``, drawn
    as :func:`~t3fast.training.step_draws.uniform` draws them."""
    dropped = uniform(command.shape, command.device, generator) < share
    return torch.where(dropped, -1, command)


def plan_error(planned: Tensor, future_actions: Tensor) -> Tensor:
    """Distance (metres) between planned and true positions ``[..., S]`` from displacements
    ``[..., S, 2]`` (broadcast: e.g. every mode ``[B, K, S, 2]`` against ``[B, 1, S, 2]``)."""
    return (planned.cumsum(-2) - future_actions.cumsum(-2)).norm(dim=-1)
