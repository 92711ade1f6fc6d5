"""What the stages of the forecast hand each other (:mod:`t3fast.forecast`)."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from t3fast.agents.boxes import AgentBoxes
from t3fast.models.triplane import Triplane


@dataclass
class Past:
    """The encoded past: ``occupancy`` labels ``[B, T, X, Y, Z]`` (each frame in its own ego
    frame, the present last), their planar ``poses`` ``[B, T, 3]`` and displacements ``actions``
    ``[B, T - 1, 2]`` in the present frame, and ``planes`` ``[B, T, C, H, W]`` in the frame the
    forecaster works in."""

    occupancy: Tensor
    poses: Tensor
    actions: Tensor
    planes: Triplane

    @property
    def present_labels(self) -> Tensor:
        """The present frame's labels ``[B, X, Y, Z]``."""
        return self.occupancy[:, -1]

    @property
    def present_planes(self) -> Triplane:
        """The present frame's triplane (planes ``[B, C, H, W]``)."""
        return self.planes.map(lambda p: p[:, -1])


@dataclass
class Agents:
    """The present's agents as the classical tracker sees them: ``velocity`` ``[B, 4, H, W]``
    (:func:`~t3fast.agents.tracker.tracker_velocities`, for a forecaster with a tracker prior,
    else None) and, for a model that draws boxes, per sample their fitted ``boxes`` and the
    component maps ``ids`` ``[B, X, Y]`` (:func:`~t3fast.agents.boxes.fit_agent_boxes`), else
    None. Fitted in fixed slots (a GPU run), ``fits`` holds every window's boxes at once
    (``[B, n, ...]``; ``boxes`` lists views of them), else None."""

    velocity: Tensor | None = None
    boxes: list[AgentBoxes] | None = None
    ids: Tensor | None = None
    fits: AgentBoxes | None = None


@dataclass
class Scene:
    """The forecaster's future triplanes ``futures`` and their changes from the present
    ``changes`` (one per step), and the flow forecaster's forward displacements of the present
    xy cells ``displacements`` ``[B, S, 2, H, W]`` (plane cells; None for the Delta forecaster)."""

    futures: list[Triplane]
    changes: list[Triplane]
    displacements: Tensor | None


@dataclass
class AgentMoves:
    """Where one sample's present agents go, for the label-space render: ``agents`` (the present
    frame's :func:`~t3fast.agents.tracker.frame_agents`), each agent's ``shift`` ``[S, n, 2]``
    (grid cells), ``as_box`` ``[n]`` (drawn as its fitted box), and the fitted boxes (``boxes``,
    or None for a model that fits none) at every step: ``box_poses`` ``[S, n, 3]`` (centre, yaw;
    present frame; only those ``as_box`` are drawn)."""

    agents: dict[str, Tensor]
    shift: Tensor
    as_box: Tensor
    boxes: AgentBoxes | None
    box_poses: Tensor | None


@dataclass
class Plan:
    """The ego's future: ``actions`` ``[B, S, 2]`` displacements and ``poses`` ``[B, S, 3]``
    (x, y, yaw), both in the present frame."""

    actions: Tensor
    poses: Tensor


@dataclass
class Forecast:
    """What :meth:`~t3fast.models.world_model.T3Former.forecast` returns for ``S`` future steps.

    Attributes:
        labels: uint8 ``[B, S, X, Y, Z]`` decoded future occupancy (argmax mode).
        triplanes: per step the predicted :class:`Triplane` (planes ``[B, C, H, W]``).
        actions: ``[B, S, 2]`` planned (or given) displacements in the present frame.
        trajectory: ``[B, S, 2]`` planned positions, ``actions.cumsum(1)``.
        poses: ``[B, S, 3]`` future ego poses (x, y, yaw) in the present frame; each labels
            frame is in the ego frame of its pose.
    """

    labels: Tensor
    triplanes: list[Triplane]
    actions: Tensor
    trajectory: Tensor
    poses: Tensor
