"""The stage-2 loss of the flow forecaster on cached ego-aligned windows: a loss that carries motion.

In the ego-aligned frame almost every cell of a future plane equals the present one, and the
ones that do not are mostly the world coming into view, not agents moving (agents cover 1-3 %
of the xy plane). A plain L1 over the plane therefore rewards copying. Here:

* ``latent``: L1 + gamma * L2 between the predicted and the encoded future xy planes, each
  cell weighted ``1 + agent_weight`` where an agent is, now or at that step (so the moving
  content carries a fixed share of the loss however small it is), else 1;
* ``flow``: per agent and step, L1 between the mean predicted forward displacement over the
  tracked cells its box covers now and the mean of its true motion there
  (:func:`~t3fast.training.world_model.motion_targets.agent_motion`): the label-space render
  moves an agent as a whole by that mean, so this is the error it makes, and each agent counts
  once whatever its size (a per-cell L1 let the many cells of buses and parked cars outweigh the
  pedestrians, and lowered it without moving agents better). Moving agents (``flow_moving``)
  and seen agents that did not move (``flow_parked``: a parked car the tracker sees drift must
  stand still) are averaged apart and added, so the few moving ones are not diluted by the
  many parked ones. Plus ``static_flow_weight`` x the displacement's size on the cells no box
  covers and no tracked agent touches. The cells of a tracked agent just outside its box (the
  ring its velocity is spread to, a plane cell it only grazes) have no target: told to stand
  still there, a motion head shrank every agent's motion.

``total = latent + flow_weight * flow`` (+ ``action_weight`` x the route planner's position
error when it trains, ``plan_l2``) (logged as ``loss``) is exactly what the gradient sees. Also logged, without
gradient: the same latent loss of the copy forecast (the present plane repeated), the bar a
forecaster has to get under.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from t3fast.data.sample import PRESENT
from t3fast.training.configs import WorldLossConfig
from t3fast.training.world_model.latent_cache import AlignedBatch
from t3fast.training.world_model.motion_targets import agent_motion
from t3fast.training.world_model.plan_loss import PlanBatch, plan_error


def latent_error(pred: Tensor, target: Tensor, weight: Tensor, gamma: float) -> Tensor:
    """Mean over cells, weighted by ``weight`` ``[B, S, H, W]``, of the channel-mean L1 + gamma
    L2; planes ``[B, S, C, H, W]``."""
    diff = pred - target
    err = diff.abs().mean(2) + gamma * diff.square().mean(2)
    return (weight * err).sum() / weight.sum()


def agent_means(values: Tensor, owner: Tensor, cells: Tensor, agents: int) -> tuple[Tensor, Tensor]:
    """Per agent, the mean of per-cell ``values`` ``[B, S, 2, H, W]`` over the cells ``cells``
    (bool ``[B, S, H, W]``) it owns (``owner`` ``[B, H, W]``, -1 none) -> (means
    ``[B, S, agents, 2]``, cell counts ``[B, S, agents]``)."""
    b, s = values.shape[:2]
    index = torch.where(cells, owner[:, None], agents).flatten(2)  # [B, S, HW]; ``agents``: no one
    sums = values.new_zeros(b, s, 2, agents + 1).scatter_add_(3, index[:, :, None].expand(-1, -1, 2, -1),
                                                               values.flatten(3))
    count = values.new_zeros(b, s, agents + 1).scatter_add_(2, index, cells.flatten(2).to(values.dtype))
    return (sums / count[:, :, None].clamp(min=1)).transpose(2, 3)[:, :, :agents], count[:, :, :agents]


@dataclass
class AgentTargets:
    """What the flow term compares, per agent ``a`` and future step ``s``: ``cells`` int64
    ``[B, H, W]`` (the agent each tracked cell under a box belongs to, -1 none: the cells the
    render moves it by), ``visible`` bool ``[B, S, A]`` (seen now and then, with tracked cells)
    and ``motion`` ``[B, S, A, 2]`` (its true mean displacement over those cells, plane cells)."""

    cells: Tensor
    visible: Tensor
    motion: Tensor


def agent_targets(target: Tensor, moving: Tensor, static: Tensor, covered: Tensor, owner: Tensor,
                  velocity: Tensor, agents: int) -> AgentTargets:
    """:class:`AgentTargets` of ``agents`` boxes (``owner`` < ``agents``) from the per-cell
    targets and masks of :func:`~t3fast.training.world_model.motion_targets.agent_motion` and the
    tracker's ``velocity`` ``[B, 4, H, W]`` (tracked cells: where it is not 0); a box that owns no
    cell is not visible."""
    tracked = (velocity != 0).any(1)  # [B, H, W]
    cells = torch.where(tracked, owner, -1)
    seen = (moving | (static & covered[:, None])) & tracked[:, None]  # whose target is known
    motion, count = agent_means(target, cells, seen, agents)
    return AgentTargets(cells, count > 0, motion)


def agent_errors(displacements: Tensor, targets: AgentTargets, min_flow: float = 0.5) -> tuple[Tensor, Tensor, Tensor]:
    """Per agent and step, the L1 between the mean forward ``displacements`` ``[B, S, 2, H, W]``
    over its cells and its true mean motion (``targets``) -> (errors ``[B, S, A]``, which agents
    moved at least ``min_flow`` cells, which were seen and did not; bool ``[B, S, A]``)."""
    b, s, _, h, w = displacements.shape
    visible, motion = targets.visible[:, :s], targets.motion[:, :s]
    owner = targets.cells.clamp(min=0).flatten(1)[:, None].expand(-1, s, -1)
    seen = (targets.cells[:, None] >= 0) & visible.gather(2, owner).view(b, s, h, w)
    predicted, _ = agent_means(displacements, targets.cells, seen, motion.shape[2])
    error = (predicted - motion).abs().sum(-1)
    is_moving = visible & (motion.norm(dim=-1) >= min_flow)
    return error, is_moving, visible & ~is_moving


def masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    """Mean of ``values`` where ``mask`` (same shape) holds; 0 where it never does."""
    return (values * mask).sum() / mask.sum().clamp(min=1)


def flow_terms(displacements: Tensor, targets: AgentTargets, min_flow: float = 0.5) -> tuple[Tensor, Tensor]:
    """``flow_moving`` and ``flow_parked`` of the module doc (see :func:`agent_errors`)."""
    error, is_moving, is_parked = agent_errors(displacements, targets, min_flow)
    return masked_mean(error, is_moving), masked_mean(error, is_parked)


def motion_loss(model: nn.Module, batch: AlignedBatch, loss: WorldLossConfig, min_flow: float = 0.5,
                plan: PlanBatch | None = None) -> tuple[Tensor, dict[str, Tensor]]:
    """Loss of the flow forecaster's six future xy planes of ``batch`` (see the module doc); an
    agent moves when its true mean motion is at least ``min_flow`` plane cells. With ``plan``
    (a route planner that trains), plus ``action_weight`` x its mean position error (metres,
    :mod:`~t3fast.training.world_model.plan_loss`), in the same forward call."""
    planes = batch.planes
    history = planes.map(lambda p: p[:, : PRESENT + 1])
    futures, displacements, _, planned = model(history, batch.velocity, None if plan is None else plan.inputs)
    pred = torch.stack([f.xy for f in futures], dim=1)  # [B, S, C, H, W]
    steps = pred.shape[1]
    target = planes.xy[:, PRESENT + 1 : PRESENT + 1 + steps]
    present = planes.xy[:, PRESENT : PRESENT + 1]
    target_disp, moving, static, agents, covered, owner = agent_motion(batch.boxes, batch.box_valid,
                                                                       tuple(pred.shape[-2:]), min_flow=min_flow)
    target_disp, moving, static, agents = (m[:, :steps] for m in (target_disp, moving, static, agents))
    weight = 1.0 + loss.agent_weight * agents.float()
    latent = latent_error(pred, target, weight, loss.gamma)
    flow_moving, flow_parked = flow_terms(
        displacements, agent_targets(target_disp, moving, static, covered, owner, batch.velocity,
                                     batch.boxes.shape[2]), min_flow)
    elsewhere = static & ~covered[:, None] & ~(batch.velocity != 0).any(1, keepdim=True)
    flow_static = (displacements.abs().sum(2) * elsewhere).sum() / elsewhere.sum().clamp(min=1)
    flow_term = flow_moving + flow_parked + loss.static_flow_weight * flow_static
    total = latent + loss.flow_weight * flow_term
    with torch.no_grad():
        copy = latent_error(present.expand_as(target), target, weight, loss.gamma)
    # the trainer logs ``total`` as ``loss``
    parts = {"latent": latent, "copy_latent": copy, "flow_moving": flow_moving, "flow_parked": flow_parked,
             "flow_static": flow_static}
    if plan is not None:
        error = plan_error(planned, plan.future_actions)
        total = total + loss.action_weight * error.mean()
        parts.update(plan_l2=error.mean(), plan_l2_3s=error[:, -1].mean())
    return total, {k: v.detach() for k, v in parts.items()}
