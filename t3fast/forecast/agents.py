"""Stage 2: the present's agents as the classical tracker sees them (:mod:`t3fast.agents`).

What a model reads of its agents is fixed by its config: a flow forecaster starts from the
tracker's velocities (measured in the last three past frames moved into the present frame),
and a model that draws its agents as boxes fits each agent's box to its
columns in every past frame."""

from __future__ import annotations

from dataclasses import fields

import torch
from torch import Tensor

from t3fast.agents.boxes import AgentBoxes, fit_agent_boxes
from t3fast.agents.tracker import agent_slots, tracker_velocities
from t3fast.forecast.records import Agents, Past
from t3fast.models.ego_motion import warp_sequence


@torch.no_grad()
def measured_velocities(occupancy: Tensor, poses: Tensor, plane_shape: tuple[int, int]) -> Tensor:
    """The tracker's agent velocities ``[B, 4, H, W]`` (plane cells per step,
    :func:`~t3fast.agents.tracker.tracker_velocities`) measured in the last three past frames of
    ``occupancy`` ``[B, T, X, Y, Z]`` moved into the present frame with ``poses`` ``[B, T, 3]``."""
    frames = torch.cat([warp_sequence(occupancy[:, -3:-1], poses[:, -3:-1]), occupancy[:, -1:]], dim=1)
    return tracker_velocities(frames, plane_shape)


@torch.no_grad()
def fitted_boxes(occupancy: Tensor, poses: Tensor) -> tuple[list[AgentBoxes], Tensor, AgentBoxes | None]:
    """Per sample, the boxes of the present's agents fitted to the past frames (labels
    ``[B, T, X, Y, Z]``, planar poses ``[B, T, 3]``; :func:`~t3fast.agents.boxes.fit_agent_boxes`);
    the present's agent maps ``[B, X, Y]`` (0 off the agents, else 1 + the agent's index); and,
    fitted in fixed slots (every window at once), the boxes of all of them ``[B, n, ...]``, which
    the list's are views of (else None)."""
    slots = agent_slots(occupancy.device)
    if slots is None:  # each window's agents counted on the host
        fits = [fit_agent_boxes(occupancy[n], poses[n]) for n in range(occupancy.shape[0])]
        return [fit for _, fit in fits], torch.stack([now["ids"] for now, _ in fits]), None
    now, fit = fit_agent_boxes(occupancy, poses, slots=slots)
    views = [AgentBoxes(**{f.name: _window(getattr(fit, f.name), n) for f in fields(fit)})
             for n in range(occupancy.shape[0])]
    return views, now["ids"], fit


def _window(value: Tensor | None, n: int) -> Tensor | None:
    return None if value is None else value[n]


class FindAgents:
    """:class:`Past` -> :class:`Agents`.

    Args:
        plane_shape: ``(H, W)`` of the xy plane the velocities are pooled on.
        velocities: measure the tracker's velocities (the flow forecaster reads them).
        boxes: fit the agents' boxes (a model that draws them).
    """

    def __init__(self, plane_shape: tuple[int, int], velocities: bool, boxes: bool):
        self.plane_shape, self.velocities, self.boxes = plane_shape, velocities, boxes

    def __call__(self, past: Past) -> Agents:
        agents = Agents()
        if self.velocities:
            agents.velocity = measured_velocities(past.occupancy, past.poses, self.plane_shape)
        if self.boxes:
            agents.boxes, agents.ids, agents.fits = fitted_boxes(past.occupancy, past.poses)
        return agents
