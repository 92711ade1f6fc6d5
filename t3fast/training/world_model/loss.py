"""The stage-2 loss of one autoregressive rollout (see :mod:`t3fast.training.world_model`)."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from t3fast.data.sample import PRESENT
from t3fast.models.triplane import Triplane
from t3fast.training.configs import WorldLossConfig
from t3fast.training.losses import occupancy_loss
from t3fast.training.sampling import sample_changed_points, sample_query_points


def rollout_history(model: nn.Module, planes: Triplane, past_actions: Tensor, future_actions: Tensor, first: int,
                    pushforward: bool) -> tuple[Triplane, Tensor]:
    """The history a rollout from future step ``first`` reads: the planes ``[B, 11, C, H, W]`` up
    to that step and the true displacements so far or, with ``pushforward``, the present's
    planes followed by the model's own predictions and plans of the ``first`` earlier steps
    (computed without gradients), as at inference -> (planes, displacements ``[B, T_p + first, 2]``)."""
    if not (pushforward and first):
        return (planes.map(lambda p: p[:, : PRESENT + 1 + first]),  # the forecaster reads the last 5
                torch.cat([past_actions, future_actions[:, :first]], dim=1))
    core = model.module if hasattr(model, "module") else model
    history = planes.map(lambda p: p[:, : PRESENT + 1])
    with torch.no_grad():
        frames, planned = core.rollout(history, past_actions, first)
    for frame in frames:
        history = history.append(frame)
    return history, torch.cat([past_actions, planned], dim=1)


def planner_trains(model: nn.Module) -> bool:
    """Whether the world model's planner (DDP-wrapped or not) has weights that train: a frozen
    planner's displacement error is logged, not added to the loss the gradient sees."""
    core = model.module if hasattr(model, "module") else model
    return any(p.requires_grad for p in core.planner.parameters())


def rollout_loss(
    model: nn.Module, planes: Triplane, occ: Tensor, past_actions: Tensor, future_actions: Tensor, first: int,
    steps: int, loss: WorldLossConfig,
) -> tuple[Tensor, dict[str, Tensor]]:
    """Stage-2 loss of one rollout of ``steps`` steps starting at future step ``first``.

    With ``loss.pushforward`` the history of step ``first`` holds the model's own predictions of
    the ``first`` earlier future steps and the planner continues from its own plan of them (both
    computed without gradients), as at inference, instead of encoded ground truth and true
    displacements: the planner is trained on its own rollouts, its errors included.

    Args:
        planes: encoded frames ``[B, 11, C, H, W]``; occ: labels ``[B, 11, X, Y, Z]``.
    """
    history, actions = rollout_history(model, planes, past_actions, future_actions, first, loss.pushforward)
    targets = [PRESENT + 1 + first + j for j in range(steps)]
    slots = (loss.num_occupied, loss.num_near_free, loss.num_far_free)
    queries = [sample_query_points(occ[:, t], *slots) for t in targets]
    if loss.num_changed:
        changed = [sample_changed_points(occ[:, t], occ[:, PRESENT], loss.num_changed) for t in targets]
        queries = [tuple(torch.cat(pair, dim=1) for pair in zip(q, c)) for q, c in zip(queries, changed)]
    futures, predicted, logits = model(history, actions, steps, first, [q[0] for q in queries])
    tri = occ_loss = torch.zeros((), device=occ.device)
    for j, t in enumerate(targets):
        for p, target in zip(futures[j], planes):
            if p is not None:
                tri = tri + F.l1_loss(p, target[:, t]) + loss.gamma * F.mse_loss(p, target[:, t])
        occ_loss = occ_loss + occupancy_loss(logits[j], queries[j][1], lovasz_weight=loss.lovasz_weight)[0]
    act = (predicted - future_actions[:, first : first + steps]).square().sum(-1).mean()
    tri, occ_loss = tri / steps, occ_loss / steps
    total = tri + loss.xi * occ_loss
    if planner_trains(model):
        total = total + loss.action_weight * act
    parts = {"triplane": tri, "occupancy": occ_loss, "action": act}
    return total, {k: v.detach() for k, v in parts.items()}
