"""The stage-2 loss of the flow forecaster on cached ego-aligned windows: a loss that carries motion.

In the ego-aligned frame almost every cell of a future plane equals the present one, and the
ones that do not are mostly the world coming into view, not agents moving (agents cover 1-3 %
of the xy plane). A plain L1 over the plane therefore rewards copying. Here:

* ``latent``: L1 + gamma * L2 between the predicted and the encoded future xy planes, each
  cell weighted ``1 + agent_weight`` where an agent is, now or at that step (so the moving
  content carries a fixed share of the loss however small it is), else 1;
* ``flow``: L1 between the predicted forward displacement of the present cells and the
  agents' motion (:func:`~t3fast.training.world_model.motion_targets.agent_motion`) on every
  cell a seen agent's box covers now, moving or parked (a parked car the tracker sees drift
  must stand still), plus ``static_flow_weight`` x the displacement's size on the cells no box
  covers and no tracked agent touches. The cells of a tracked agent just outside its box (the
  ring its velocity is spread to, a plane cell it only grazes) have no target: told to stand
  still there, a motion head shrank every agent's motion, as the render moves an agent by the
  mean over all its cells.

``total = latent + flow_weight * flow`` (logged as ``loss``) is exactly what the gradient sees. Also logged, without
gradient: the same latent loss of the copy forecast (the present plane repeated), the bar a
forecaster has to get under.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from t3fast.data.sample import PRESENT
from t3fast.training.configs import WorldLossConfig
from t3fast.training.world_model.latent_cache import AlignedBatch
from t3fast.training.world_model.motion_targets import agent_motion


def _latent_error(pred: Tensor, target: Tensor, weight: Tensor, gamma: float) -> Tensor:
    """Weighted mean over cells of the channel-mean L1 + gamma L2; planes ``[B, S, C, H, W]``."""
    diff = pred - target
    err = diff.abs().mean(2) + gamma * diff.square().mean(2)
    return (weight * err).sum() / weight.sum()


def motion_loss(model: nn.Module, batch: AlignedBatch, loss: WorldLossConfig) -> tuple[Tensor, dict[str, float]]:
    """Loss of the flow forecaster's six future xy planes of ``batch`` (see the module doc)."""
    planes = batch.planes
    history = planes.map(lambda p: p[:, : PRESENT + 1])
    futures, displacements, _ = model(history, batch.past_actions, motion=True, velocity=batch.velocity)
    pred = torch.stack([f.xy for f in futures], dim=1)  # [B, S, C, H, W]
    steps = pred.shape[1]
    target = planes.xy[:, PRESENT + 1 : PRESENT + 1 + steps]
    present = planes.xy[:, PRESENT : PRESENT + 1]
    target_disp, moving, static, agents, covered = agent_motion(batch.boxes, batch.box_valid, tuple(pred.shape[-2:]))
    target_disp, moving, static, agents = (m[:, :steps] for m in (target_disp, moving, static, agents))
    parked = static & covered[:, None]
    tracked = (batch.velocity != 0).any(1, keepdim=True)  # [B, 1, H, W]
    elsewhere = static & ~covered[:, None] & ~tracked
    weight = 1.0 + loss.agent_weight * agents.float()
    latent = _latent_error(pred, target, weight, loss.gamma)
    flow_error = (displacements - target_disp).abs().sum(2)  # on parked cells: the displacement's size
    flow_moving = (flow_error * moving).sum() / moving.sum().clamp(min=1)
    flow_parked = (flow_error * parked).sum() / parked.sum().clamp(min=1)
    boxed = (flow_error * (moving | parked)).sum() / (moving | parked).sum().clamp(min=1)
    flow_static = (displacements.abs().sum(2) * elsewhere).sum() / elsewhere.sum().clamp(min=1)
    flow_term = boxed + loss.static_flow_weight * flow_static
    total = latent + loss.flow_weight * flow_term
    with torch.no_grad():
        copy = _latent_error(present.expand_as(target), target, weight, loss.gamma)
    # the trainer logs ``total`` as ``loss``
    parts = {"latent": latent, "copy_latent": copy, "flow_moving": flow_moving, "flow_parked": flow_parked,
             "flow_static": flow_static}
    return total, {k: float(v.detach()) for k, v in parts.items()}
