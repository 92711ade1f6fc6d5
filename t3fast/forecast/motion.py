"""Stage 4: where each of the present's agents goes, for a model that draws its agents.

Every agent (8-connected BEV component of vehicle and human columns,
:func:`~t3fast.agents.tracker.frame_agents`) moves as a whole by the mean of the flow
forecaster's displacement over its columns: the tracker's velocity corrected by the motion head
(:meth:`~t3fast.models.flow_forecaster.FlowTriplaneForecaster.tracked_motion`; untrained, exactly
the tracker). An agent with a trusted fitted box (:mod:`t3fast.agents.boxes`) is drawn as that
box, moved by the same displacement without rounding it to cells or, with a box motion network
(:mod:`t3fast.models.box_motion`), placed where that network says."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.agents.box_kinematics import ego_step
from t3fast.agents.boxes import AgentBoxes
from t3fast.agents.tracker import agent_slots, component_shifts, frame_agents, frame_of
from t3fast.data.classes import AGENT_CLASSES, VOXEL_SIZE
from t3fast.forecast.records import AgentMoves, Agents, Past, Scene
from t3fast.models.box_motion import BoxMotionNet, predict_box_poses


class MoveAgents:
    """(:class:`Past`, :class:`Agents`, :class:`Scene`) -> per sample :class:`AgentMoves`.

    Args:
        box_motion: the network that places the fitted boxes; None moves them with the
            forecaster's displacement.
    """

    def __init__(self, box_motion: BoxMotionNet | None):
        self.box_motion = box_motion

    @torch.no_grad()
    def __call__(self, past: Past, agents: Agents, scene: Scene) -> list[AgentMoves]:
        present = past.present_labels
        slots = agent_slots(present.device)
        if slots is None:  # each window's agents counted on the host
            found = [frame_agents(present[n], AGENT_CLASSES) for n in range(present.shape[0])]
            shifts = [component_shifts(now, scene.displacements[n]) for n, now in enumerate(found)]
        else:  # every window's at once
            every = frame_agents(present, AGENT_CLASSES, slots)
            found = [frame_of(every, n) for n in range(present.shape[0])]
            shifts = component_shifts(every, scene.displacements).unbind(0)
        return [self._move(past, n, now, shift, agents.boxes[n] if agents.boxes is not None else None, agents.ids)
                for n, (now, shift) in enumerate(zip(found, shifts, strict=True))]

    def _move(self, past: Past, n: int, now: dict[str, Tensor], shift: Tensor, fitted: AgentBoxes | None,
              ids: list[Tensor] | None) -> AgentMoves:
        """Sample ``n``'s moves: its agents ``now``, their ``shift`` ``[S, n, 2]`` and ``fitted`` boxes."""
        if fitted is None:
            return AgentMoves(now, shift, now["cls"].new_zeros(now["cls"].shape[0], dtype=torch.bool), None, None)
        if fitted.label.shape[0] != now["cls"].shape[0]:
            raise ValueError(f"{fitted.label.shape[0]} fitted boxes for the {now['cls'].shape[0]} agents "
                             "of the present frame: fit them on the same frames")
        if self.box_motion is not None:
            poses = predict_box_poses(self.box_motion, past.occupancy[n, -1], fitted, ids[n], ego_step(past.poses[n]))
        else:
            centre = fitted.centre + shift.to(fitted.centre.device) * VOXEL_SIZE
            poses = torch.cat([centre, fitted.yaw.expand(shift.shape[0], -1)[..., None]], -1)
        return AgentMoves(now, shift, fitted.drawn, fitted, poses)
