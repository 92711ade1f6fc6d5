"""Agents as boxes fitted to their voxel columns in every observed frame, and drawn exactly.

Moving an agent's present voxels by a whole number of cells loses what a box at a sub-cell
position looks like: a column is occupied when its centre lies inside the box's footprint, so a
0.6 m pedestrian covers one to four 0.4 m columns depending on where in the cells it stands.
One frame does not tell where the box is within its columns, but each past frame samples it at
another offset (the agent and the ego move), so a box fitted to all of them jointly (centre,
velocity, acceleration, heading, length and width: each past frame's columns taken exactly into
the present frame with its pose, no resampling) pins it down to a few centimetres. Drawn at its
forecast position, its footprint is what the voxelised future shows (40 validation windows
along the true poses, agents drawn from their true present boxes moved by their true last-step
velocity: moving-class mIoU 47.4, against 40.9 moving their voxels by the same velocity rounded
to cells; ``benchmarks/tools/motion_ceilings.py``).

Each present agent (8-connected BEV component of vehicle and human columns,
:func:`~t3fast.agents.tracker.frame_agents`) is followed back through the past frames
(nearest component of its class to where its last velocity puts it), and its box is the one
whose footprint best separates the agent's columns from the columns around them in every
frame where it was found: a soft inside/outside (a sigmoid of the signed distance to the
footprint's edge, sharpened over the iterations) fitted by Adam on its closed-form gradient,
all agents of a window at once in one fused op (:func:`t3fast.ops.box_fit`: no autograd, no
host synchronisation, one launch pair on the GPU).
An agent is drawn as a box only where the fit explains its columns (IoU >= ``MIN_FIT_IOU``), it
is of one class and it was seen in two frames or more; queued cars merged into one component
or a truck with its trailer are not boxes, and move as voxels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from t3fast import ops
from t3fast.agents.tracker import (
    agent_levels,
    cell_metres,
    follow_agents,
    frame_agents,
    frame_of,
    slot_sums,
    slot_values,
)
from t3fast.data.classes import AGENT_CLASSES, GRID_LOWER, VOXEL_SIZE

MIN_FIT_IOU = 0.5  # footprint IoU over the agent's frames under which it is not drawn as a box
# Adam steps; 200 steps and samples 2 cells out scored the same on 16 validation windows (47.65
# against 47.64 moving-class mIoU along the true poses) at 1.8x the cost
FIT_ITERS = 100
FIT_LR = 0.02  # metres (radians, log-metres) per Adam step
SOFTNESS = (0.1, 0.015)  # metres: the sigmoid's width at the first and the last iteration
NEAR = 1  # cells from an agent's columns that its fit samples (the farther ones say nothing)
MAX_REACH = 21.0  # cells: an agent reaching farther from its centroid (less 3) is not fitted
# weight of a zero-acceleration prior (per agent, in (m/step^2)^2) beside the mean fit loss per
# column: a vehicle speeding up or braking moves at its 2 s mean velocity plus 1 s of its
# acceleration, so the fit's present velocity takes the acceleration it can see. Median error
# against the true last step, moving agents of 10 held-out training scenes, constant velocity ->
# this: car 0.28 -> 0.09 m/step, bus 0.21 -> 0.09, truck 0.21 -> 0.10, trailer 0.18 -> 0.06,
# motorcycle 0.25 -> 0.15, pedestrian 0.036 both; standing agents 0.010 -> 0.021. Weights 0, 1,
# 10 and 30 did worse.
ACCEL_PRIOR = 3.0
#: columns from a drawn box's centre column within which its footprint is tested: the half
#: diagonal of a 20 m x 5 m box (a fitted agent spans at most MAX_REACH + 3 cells from its centroid)
DRAW_REACH = 26


@dataclass
class AgentBoxes:
    """Fitted boxes of one frame's agents (per slot of :func:`frame_agents`, ``n`` of them; an
    empty slot is never drawn), in the present frame, metres: ``centre`` ``[n, 2]``,
    ``velocity`` ``[n, 2]`` per step (the present one), ``yaw`` ``[n]``, ``length``, ``width``
    ``[n]``; ``bottom``, ``top`` ``[n]`` the levels the agent's voxels span (top exclusive);
    ``label`` ``[n]`` its class; ``drawn`` ``[n]`` bool: the fit is trusted and the agent is
    drawn as this box; ``track`` ``[n, T, 2]`` the agent's column centroid in each observed frame
    (present frame, metres; NaN where it was not found); ``future`` ``[S, n, 3]`` where a learned
    motion (:mod:`t3fast.models.box_motion`) placed each box at every future step (centre, yaw;
    present frame), None to move them by their fitted velocity."""

    centre: Tensor
    velocity: Tensor
    yaw: Tensor
    length: Tensor
    width: Tensor
    bottom: Tensor
    top: Tensor
    label: Tensor
    drawn: Tensor
    track: Tensor | None = None
    future: Tensor | None = None


def fit_agent_boxes(frames: Tensor, poses: Tensor, iters: int = FIT_ITERS,
                    slots: int | None = None) -> tuple[dict[str, Tensor], AgentBoxes]:
    """Boxes of the present frame's agents fitted to their columns in every observed frame.

    Args:
        frames: labels ``[T, X, Y, Z]`` of the past frames and the present (last), each in its
            own ego frame; with ``slots``, the frames of several windows may come at once
            (``[..., T, X, Y, Z]``: every result then has the leading dims too).
        poses: their planar poses ``[..., T, 3]`` in the present frame (the last is zero).
        slots: the agents' slots per frame (:func:`~t3fast.agents.tracker.frame_agents`; None:
            as many as the frame holds, counted on the host).
    Returns:
        the present's agents (:func:`~t3fast.agents.tracker.frame_agents`) and their
        :class:`AgentBoxes` (one per slot; an empty slot is not drawn).
    """
    lead = frames.shape[:-4]
    if frames.dim() < 4 or poses.shape != (*frames.shape[:-3], 3) or (lead and slots is None):
        raise ValueError(f"fit_agent_boxes: frames must be [T, X, Y, Z] and poses [T, 3] (with slots, both may have "
                         f"leading dims), got {list(frames.shape)} and {list(poses.shape)}")
    poses = poses.to(frames.device, torch.float64)
    if slots is None:
        agents = [frame_agents(f, AGENT_CLASSES) for f in frames]
    else:  # every frame in one call
        every = frame_agents(frames, AGENT_CLASSES, slots)
        agents = [frame_of(every, t, len(lead)) for t in range(frames.shape[-4])]
    now = agents[-1]
    n = now["cls"].shape[-1]
    empty = poses.new_zeros(n)
    if n == 0:
        return now, AgentBoxes(empty.view(0, 2), empty.view(0, 2), empty, empty, empty, empty.long(),
                               empty.long(), now["cls"], empty.bool(), empty.view(0, frames.shape[0], 2))
    match = follow_agents(agents, poses)
    found = _centroids(agents, match)
    # each column's offset from its agent's centroid (columns off the agents gather in slot n)
    owner = now["column_slot"]
    offset = now["columns"].double() - slot_values(now["centroid"], owner)
    spread = _per_slot_max(offset.norm(dim=-1), owner, n)
    # start: the present centroid, the last step's velocity, the principal axis and extents
    centre = cell_metres(now["centroid"], poses[..., -1:, :])
    velocity = torch.zeros_like(centre)
    if match.shape[-1] > 1:
        velocity = torch.where(match[..., -2:-1] >= 0, centre - cell_metres(found[..., -2, :], poses[..., -2:-1, :]),
                               velocity)
    spread_m = offset * VOXEL_SIZE
    cov = slot_sums(spread_m[..., :, None] * spread_m[..., None, :], owner, n)
    axis = principal_axis(cov)
    column_axis = slot_values(axis, owner)
    along = (spread_m * column_axis).sum(-1).abs()
    across = (spread_m[..., 1] * column_axis[..., 0] - spread_m[..., 0] * column_axis[..., 1]).abs()
    length = _per_slot_max(along, owner, n) * 2 + VOXEL_SIZE
    width = _per_slot_max(across, owner, n) * 2 + VOXEL_SIZE
    start = torch.cat([centre, velocity, torch.atan2(axis[..., 1], axis[..., 0])[..., None], length.log()[..., None],
                       width.log()[..., None]], -1)
    # farther: merged agents (a queue, a truck and its trailer), not fitted
    reach = torch.where(now["valid"] & (spread + 3 <= MAX_REACH), spread + 3, 0.0)
    windows = (-1,) if lead else (1,)  # the fit's batch of windows
    ids = torch.stack([a["ids"] for a in agents], -3)
    params, iou = ops.box_fit(*(t.reshape(*windows, *t.shape[len(lead):]) for t in (ids, match, found, poses, start,
                                                                                      reach)),
                              GRID_LOWER[:2], VOXEL_SIZE, math.ceil(MAX_REACH), NEAR, iters, FIT_LR, SOFTNESS,
                              ACCEL_PRIOR)
    params, iou = params.view(*lead, n, -1), iou.view(*lead, n)
    centre, velocity, yaw = params[..., :2], params[..., 2:4], params[..., 4]
    length, width = params[..., 5].exp(), params[..., 6].exp()
    votes = now["votes"]
    drawn = (iou >= MIN_FIT_IOU) & (votes.max(-1).values == votes.sum(-1)) & ((match >= 0).sum(-1) >= 2)
    return now, AgentBoxes(centre, velocity, yaw, length, width, *agent_levels(now), now["cls"], drawn & now["valid"],
                           cell_metres(found, poses[..., None, :, :]))


def principal_axis(cov: Tensor) -> Tensor:
    """The unit eigenvector ``[..., 2]`` of the larger eigenvalue of symmetric 2 x 2 matrices
    ``cov`` ``[..., 2, 2]``, in closed form: at angle ``atan2(2 b, a - c) / 2`` in
    ``(-pi/2, pi/2]`` (x >= 0), along x where the matrix is isotropic. (``torch.linalg.eigh``
    picks each vector's sign by its solver, LAPACK's on the CPU and cuSOLVER's on a GPU, and
    checks its convergence on the host: a wait on a GPU.)"""
    a, b, c = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    angle = 0.5 * torch.atan2(2 * b, a - c)
    return torch.stack([angle.cos(), angle.sin()], -1)


def _per_slot_max(values: Tensor, owner: Tensor, slots: int) -> Tensor:
    """The largest of per-column ``values`` ``[..., N]`` over each slot's columns (``owner``, the
    ``column_slot`` of :func:`~t3fast.agents.tracker.frame_agents`; at least 0): ``[..., slots]``."""
    return values.new_zeros(*owner.shape[:-1], slots + 1).scatter_reduce_(-1, owner, values, "amax",
                                                                          include_self=True)[..., :slots]


def _centroids(agents: list[dict[str, Tensor]], match: Tensor) -> Tensor:
    """Each followed agent's column centroid in every frame (:func:`follow_agents`' ``match``
    ``[..., n, T]``), in that frame's cells: ``[..., n, T, 2]``, NaN where it was not found."""
    found = []
    for t, frame in enumerate(agents):
        centroid = frame["centroid"]  # and a last slot: not found
        centroid = torch.cat([centroid, centroid.new_full((*centroid.shape[:-2], 1, 2), math.nan)], -2)
        index = torch.where(match[..., t] >= 0, match[..., t], centroid.shape[-2] - 1)
        found.append(torch.take_along_dim(centroid, index[..., None], dim=-2))
    return torch.stack(found, -2)


def draw_agent_boxes(volume: Tensor, centre: Tensor, yaw: Tensor, length: Tensor, width: Tensor, bottom: Tensor,
                     top: Tensor, label: Tensor, pose: Tensor) -> None:
    """Draw boxes into label volumes ``[..., X, Y, Z]`` (uint8) in place: box ``i`` (centre
    ``[..., m, 2]``, yaw ``[..., m]`` in the present frame, metres; length, width ``[m]``) fills
    the levels ``bottom[i]`` to ``top[i]`` (exclusive) of every column whose centre lies inside
    its footprint, and the column under its centre, with ``label[i]``; where boxes overlap, the
    later one's. Length, width, bottom, top and label ``[m]`` are every volume's; ``[..., m]``
    (broadcast to the volumes' leading dims), each volume's: several windows' boxes at once.
    ``pose`` ``[..., 3]``: each volume's ego pose in the present frame (the boxes are taken into
    it); the leading dims (a forecast's steps, say) are drawn in one call. The footprint test is
    :func:`~t3fast.data.classes.box_footprint`'s, for all boxes at once on the volume's device
    (:func:`t3fast.ops.draw_boxes`), within ``DRAW_REACH`` columns of each box's centre column."""
    device = volume.device
    frames = volume.reshape(-1, *volume.shape[-3:])
    lead = volume.shape[:-3]

    def each_volume(t: Tensor) -> Tensor:  # [m] stays every volume's; [..., m] becomes [B, m]
        return t.to(device) if t.dim() == 1 else t.to(device).expand(*lead, t.shape[-1]).reshape(frames.shape[0], -1)

    pose = pose.to(device, torch.float64).reshape(frames.shape[0], 3)
    c, s = torch.cos(pose[:, 2:]), torch.sin(pose[:, 2:])  # [B, 1]
    d = centre.to(device, torch.float64).reshape(frames.shape[0], -1, 2) - pose[:, None, :2]
    heading = yaw.to(device, torch.float64).reshape(frames.shape[0], -1) - pose[:, 2:]
    half = torch.stack([each_volume(length), each_volume(width)], -1).to(torch.float64).expand_as(d) / 2
    boxes = torch.cat([torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1],
                                    torch.cos(heading), torch.sin(heading)], -1), half], -1)
    levels = torch.stack([each_volume(bottom), each_volume(top)], -1).to(torch.long)
    drawn = ops.draw_boxes(frames, boxes, levels, each_volume(label).to(torch.uint8), GRID_LOWER[:2], VOXEL_SIZE,
                           DRAW_REACH)
    volume.copy_(drawn.view(volume.shape))
