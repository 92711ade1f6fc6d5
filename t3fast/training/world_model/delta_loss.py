"""The stage-2 loss of the papers' Delta forecaster on cached ego-aligned windows.

The labels path (:func:`~t3fast.training.world_model.loss.rollout_loss`) moves and encodes each
window in the step and decodes the predictions at sampled label points: about 3 s a sample on
a 2-core CPU. Read from the aligned cache (:mod:`~t3fast.training.world_model.latent_cache`) a
sample costs the forecaster only (about 0.6 s), so the Delta forecaster trains on as many
windows as the flow forecaster.

Per sample, one rollout of ``loss.rollout_steps`` steps from future step ``first``: its history
is the encoded truth up to that step and the true displacements (teacher forcing) or, with
``loss.pushforward``, the model's own predictions and plans of the earlier steps, made without
gradient (about twice the cost). Per predicted step, the latent loss of the flow forecaster's
:mod:`~t3fast.training.world_model.motion_loss`: on the xy plane L1 + gamma L2 with the cells
an agent's box covers now or then weighted ``1 + agent_weight`` (agents cover 1-3 % of the
plane; unweighted, the loss rewards copying), on the xz and yz planes unweighted (their cells
mix every agent along a row). The cache holds planes, not labels, so there is no occupancy
term; the planner's displacement error is added when the planner trains.

``total`` (logged as ``loss``) is what the gradient sees; ``copy_latent`` (the present planes
repeated, no gradient) is the bar to get under.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from t3fast.data.sample import NUM_FUTURE, PRESENT
from t3fast.training.configs import WorldLossConfig
from t3fast.training.world_model.latent_cache import AlignedBatch
from t3fast.training.world_model.loss import planner_trains, rollout_history
from t3fast.training.world_model.motion_loss import latent_error
from t3fast.training.world_model.motion_targets import agent_cells

PLANES = ("xy", "xz", "yz")


def delta_rollout_loss(model: nn.Module, batch: AlignedBatch, loss: WorldLossConfig,
                       first: int) -> tuple[Tensor, dict[str, Tensor]]:
    """Loss of ``loss.rollout_steps`` predicted steps of ``batch`` from future step ``first``
    (see the module doc); the model is a :class:`~t3fast.training.world_model.forwards.RolloutModel` with the
    Delta forecaster (or DDP around one)."""
    steps = loss.rollout_steps
    if not 0 <= first <= NUM_FUTURE - steps:
        raise ValueError(f"a {steps}-step rollout starts at a future step in [0, {NUM_FUTURE - steps}], got {first}")
    planes = batch.planes
    history, actions = rollout_history(model, planes, batch.past_actions, batch.future_actions, first,
                                       loss.pushforward)
    futures, predicted, _ = model(history, actions, steps, first)
    targets = slice(PRESENT + 1 + first, PRESENT + 1 + first + steps)
    agents = agent_cells(batch.boxes, batch.box_valid, range(targets.start, targets.stop),
                         tuple(planes.xy.shape[-2:]))
    latent = copy = predicted.new_zeros(())
    for name in PLANES:
        truth = getattr(planes, name)
        if truth is None:  # the BEV-only latent
            continue
        target = truth[:, targets]
        pred = torch.stack([getattr(f, name) for f in futures], dim=1)  # [B, S, C, H, W]
        weight = (1.0 + loss.agent_weight * agents.to(pred.dtype) if name == "xy"
                  else pred.new_ones(target.shape[:2] + target.shape[3:]))
        latent = latent + latent_error(pred, target, weight, loss.gamma)
        with torch.no_grad():
            copy = copy + latent_error(truth[:, PRESENT : PRESENT + 1].expand_as(target), target, weight, loss.gamma)
    action = (predicted - batch.future_actions[:, first : first + steps]).square().sum(-1).mean()
    total = latent + loss.action_weight * action if planner_trains(model) else latent
    parts = {"latent": latent, "copy_latent": copy, "action": action}
    return total, {k: v.detach() for k, v in parts.items()}
