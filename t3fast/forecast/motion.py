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
        windows = range(present.shape[0])
        slots = agent_slots(present.device)
        if slots is None:  # each window's agents counted on the host
            found = [frame_agents(present[n], AGENT_CLASSES) for n in windows]
            shifts = [component_shifts(now, scene.displacements[n]) for n, now in enumerate(found)]
            poses = [None if agents.boxes is None else self._poses(past.occupancy[n], past.poses[n], agents.boxes[n],
                                                                   agents.ids[n], shifts[n], found[n]) for n in windows]
        else:  # every window's at once
            every = frame_agents(present, AGENT_CLASSES, slots)
            found = [frame_of(every, n) for n in windows]
            shift = component_shifts(every, scene.displacements)
            shifts = shift.unbind(0)
            poses = [None] * len(windows) if agents.fits is None else self._poses(
                past.occupancy, past.poses, agents.fits, agents.ids, shift, every).unbind(0)
        return [self._moves(now, shift, agents.boxes[n] if agents.boxes is not None else None, poses[n])
                for n, (now, shift) in enumerate(zip(found, shifts, strict=True))]

    def _poses(self, occupancy: Tensor, poses: Tensor, fitted: AgentBoxes, ids: Tensor, shift: Tensor,
               now: dict[str, Tensor]) -> Tensor:
        """Where the ``fitted`` boxes go ``[..., S, n, 3]``, for one window's agents ``now`` (or
        every window's: leading dims ``[...]`` throughout) shifted by ``shift`` ``[..., S, n, 2]``;
        its past labels ``occupancy`` ``[..., T, X, Y, Z]``, poses ``[..., T, 3]``, agent map ``ids``."""
        if fitted.label.shape[-1] != now["cls"].shape[-1]:
            raise ValueError(f"{fitted.label.shape[-1]} fitted boxes for the {now['cls'].shape[-1]} agents "
                             "of the present frame: fit them on the same frames")
        if self.box_motion is not None:
            return predict_box_poses(self.box_motion, occupancy[..., -1, :, :, :], fitted, ids, ego_step(poses))
        centre = fitted.centre[..., None, :, :] + shift.to(fitted.centre.device) * VOXEL_SIZE
        return torch.cat([centre, fitted.yaw[..., None, :, None].expand(*centre.shape[:-1], 1)], -1)

    @staticmethod
    def _moves(now: dict[str, Tensor], shift: Tensor, fitted: AgentBoxes | None, poses: Tensor | None) -> AgentMoves:
        """A window's moves: its agents ``now``, their ``shift`` ``[S, n, 2]``, ``fitted`` boxes and their ``poses``."""
        if fitted is None:
            return AgentMoves(now, shift, now["cls"].new_zeros(now["cls"].shape[0], dtype=torch.bool), None, None)
        return AgentMoves(now, shift, fitted.drawn, fitted, poses)
