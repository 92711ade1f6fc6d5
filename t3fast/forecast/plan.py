"""Stage 5: the ego's future, planned (the route planner or Phi_act) or given (a steered forecast)."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.forecast.records import Past, Plan, Scene
from t3fast.models.ego_motion import displacements_from_poses, extrapolate_poses, poses_from_displacements
from t3fast.models.planner import MotionPlanner, constant_turn_rate
from t3fast.models.route_planner import RoutePlanner


def planned_poses(
    actions: Tensor, past_actions: Tensor, past_poses: Tensor | None = None, min_step: float = 0.2
) -> Tensor:
    """Future poses ``[B, S, 3]`` for planned displacements ``actions`` ``[B, S, 2]``: positions
    are their cumulative sum. Headings continue the observed yaw rate of the past poses
    ``[B, T, 3]`` (:func:`extrapolate_poses`), each turned by the angle between the planned
    displacement and that of constant speed and turn rate (:func:`constant_turn_rate` of
    ``past_actions``) where both move at least ``min_step`` metres (slower, a direction is
    noise: a 5 cm correction to a standing ego would swing its heading anywhere). A heading
    read from positions alone is noisier (0.6 degrees mean error one step ahead on validation
    windows, against 0.3 from the past yaw rate). Without past poses, the direction of travel."""
    if past_poses is None:
        return poses_from_displacements(actions)
    steps = actions.shape[1]
    base = constant_turn_rate(past_actions, steps)
    cross = base[..., 0] * actions[..., 1] - base[..., 1] * actions[..., 0]
    turn = torch.atan2(cross, (base * actions).sum(-1))
    moving = (base.norm(dim=-1) >= min_step) & (actions.norm(dim=-1) >= min_step)
    heading = extrapolate_poses(past_poses, steps)[..., 2] + torch.where(moving, turn, torch.zeros_like(turn))
    return torch.cat([actions.cumsum(1), heading.unsqueeze(-1)], dim=-1)


def given_plan(future_actions: Tensor) -> Plan:
    """The plan of a steered forecast: ``future_actions`` ``[B, S, 2]`` displacements or
    ``[B, S, 3]`` poses (x, y, yaw) in the present frame; displacements head along their travel."""
    if future_actions.shape[-1] == 3:
        return Plan(displacements_from_poses(future_actions), future_actions)
    return Plan(future_actions, poses_from_displacements(future_actions))


class RoutePlan:
    """The route planner (:mod:`t3fast.models.route_planner`): every step from the present, its
    road ahead in the present and previous xy planes, the past motion and the route command."""

    def __init__(self, planner: RoutePlanner):
        self.planner = planner

    @torch.no_grad()
    def __call__(self, past: Past, scene: Scene, command: Tensor | None) -> Plan:
        steps = len(scene.futures)
        actions = self.planner(past.planes.xy[:, -1], past.planes.xy[:, -2], past.actions, command)[:, :steps]
        return Plan(actions, planned_poses(actions, past.actions, past.poses))


class PhiActPlan:
    """The papers' planner Phi_act (:class:`~t3fast.models.planner.MotionPlanner`): reads the
    present and the forecast triplanes and their changes; no route command."""

    def __init__(self, planner: MotionPlanner):
        self.planner = planner

    @torch.no_grad()
    def __call__(self, past: Past, scene: Scene, command: Tensor | None) -> Plan:
        actions = self.planner(past.present_planes, scene.futures, scene.changes, past.actions, 0)
        return Plan(actions, planned_poses(actions, past.actions, past.poses))
