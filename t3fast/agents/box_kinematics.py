"""The fitted agent boxes' kinematics: what the box motion network reads and how its output moves a box.

A box fitted to an agent's past frames (:mod:`t3fast.agents.boxes`) gives its constant velocity
over 2 s; moving the box along it is the classical box tracker, the motion prior that
:class:`~t3fast.models.box_motion.BoxMotionNet` corrects. Per agent, in its own frame (x along
its heading, y to its left):

* :func:`kinematics`: the fitted velocity and speed, how its centroid in each past frame departs
  from that constant velocity (an agent speeding up or braking), its class and size;
* :func:`context_map` cropped by :func:`crop_context`: ``CROP`` cells of ``CROP_CELL`` metres from
  ``CROP_BEHIND`` metres behind it to 24 m ahead and 8 m to each side: the drivable surface, the
  walkable ground, obstacles, vehicles, people and riders, and every agent's fitted velocity;
* :func:`future_poses`: the boxes' poses at every future step from the constant velocity plus a
  correction; an agent whose fitted speed says it stands (:data:`STILL_STEP`) keeps its present pose.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

from t3fast.agents.boxes import AgentBoxes
from t3fast.agents.tracker import column_slots, slot_values
from t3fast.data.classes import (
    BARRIER,
    BICYCLE,
    BUS,
    CAR,
    CONSTRUCTION_VEHICLE,
    DRIVEABLE_SURFACE,
    EGO_LENGTH,
    EGO_WIDTH,
    GRID_LOWER,
    MANMADE,
    MOTORCYCLE,
    OTHER_FLAT,
    OTHERS,
    PEDESTRIAN,
    SIDEWALK,
    TERRAIN,
    TRAFFIC_CONE,
    TRAILER,
    TRUCK,
    VEGETATION,
    VOXEL_SIZE,
    box_footprint,
    in_classes,
)
from t3fast.device_constants import device_constant, made_once
from t3fast.models.ego_motion import rotate

#: BEV groups of the context map: a column belongs to every group one of its voxels is in
CONTEXT_GROUPS: tuple[tuple[int, ...], ...] = (
    (DRIVEABLE_SURFACE,),
    (OTHER_FLAT, SIDEWALK, TERRAIN),
    (OTHERS, BARRIER, TRAFFIC_CONE, MANMADE, VEGETATION),
    (BUS, CAR, CONSTRUCTION_VEHICLE, TRAILER, TRUCK),
    (BICYCLE, MOTORCYCLE, PEDESTRIAN),
)
VEHICLES = 3  # the group of the vehicles, the ego's
CONTEXT_CHANNELS = len(CONTEXT_GROUPS) + 2  # the groups and the agents' velocity (x, y)
BOX_CLASSES = (BICYCLE, BUS, CAR, CONSTRUCTION_VEHICLE, MOTORCYCLE, PEDESTRIAN, TRAILER, TRUCK)
CROP = (64, 32)  # crop cells along and across the agent's heading
CROP_CELL = 0.5  # metres per crop cell
CROP_BEHIND = 8.0  # metres of the crop behind the agent's centre
MOVING_STEP = 0.1  # metres per step above which an agent's frame follows its velocity, not its box
# metres per step (0.4 m/s) of fitted present speed under which an agent stands: it keeps its
# present pose, whatever the network says. The fit's velocity of a standing agent is 0.03-0.04
# m/step off and the network moved standing cars 0.18 m and pedestrians 0.28 m by the last step
# (median; its present box: 0.06 and 0.12); the slowest walkers go 0.5 m/step. On 40 windows
# of unused training scenes 1120-1129 along the true poses: moving-class mIoU 41.85 -> 42.57
# (0.1 m/step: 42.49; a still pedestrian's landing error grows again above 0.2)
STILL_STEP = 0.2


def ego_step(poses: Tensor) -> Tensor:
    """The ego's last step ``[..., 2]`` (metres, present frame) from the planar poses ``[..., T, 3]``
    of the observed frames in the present frame: from the previous pose to the origin."""
    return -poses[..., -2, :2]


def agent_headings(boxes: AgentBoxes) -> Tensor:
    """Each agent's frame heading ``[..., n]``: the direction of its fitted velocity where it moves
    (the box's yaw says nothing of forward or backward), else its box yaw."""
    v = boxes.velocity
    moving = v.norm(dim=-1) > MOVING_STEP
    return torch.where(moving, torch.atan2(v[..., 1], v[..., 0]), boxes.yaw)


def kinematics(boxes: AgentBoxes, heading: Tensor) -> Tensor:
    """Per agent ``[..., n, F]`` float32: the fitted velocity in its frame (metres per step), its
    speed, per past frame the centroid's departure from the constant velocity (its frame, metres)
    and whether it was seen, the class (one-hot over :data:`BOX_CLASSES`), length and width."""
    if boxes.track is None:
        raise ValueError("BoxMotionNet reads the agents' tracks: fit the boxes with fit_agent_boxes")
    track = boxes.track
    frames = track.shape[-2]
    seen = ~track.isnan().any(-1)
    ago = -torch.arange(frames - 1, 0, -1, dtype=track.dtype, device=track.device)  # the past frames' times, in steps
    expected = track[..., -1:, :] + ago[:, None] * boxes.velocity[..., None, :]
    departure = rotate(torch.nan_to_num(track[..., :-1, :] - expected),
                       -heading[..., None].expand(*heading.shape, frames - 1))
    departure = departure * seen[..., :-1, None]
    velocity = rotate(boxes.velocity, -heading)
    label = boxes.label
    classes = (label[..., None] == device_constant(BOX_CLASSES, label.dtype, label.device)).to(track.dtype)
    return torch.cat([velocity, boxes.velocity.norm(dim=-1, keepdim=True), departure.flatten(-2),
                      seen[..., :-1].to(track.dtype), classes, boxes.length[..., None], boxes.width[..., None]],
                     -1).float()


def kinematic_features(frames: int) -> int:
    """Width of :func:`kinematics` for ``frames`` observed frames."""
    return 3 + 3 * (frames - 1) + len(BOX_CLASSES) + 2


def context_map(present: Tensor, boxes: AgentBoxes, agent_ids: Tensor, ego_velocity: Tensor) -> Tensor:
    """The scene the agents drive in, ``[..., CONTEXT_CHANNELS, X, Y]`` float32: per BEV column of
    the present labels ``[..., X, Y, Z]``, which of :data:`CONTEXT_GROUPS` it holds, and on the
    columns of each agent (``agent_ids`` ``[..., X, Y]``: 0 off the agents, else 1 + its index in
    ``boxes``) its fitted velocity (metres per step, present frame). The ego is a vehicle too (the
    agents behind it follow it), though the labels leave it out: its footprint at the origin is
    drawn into the vehicles with its ``ego_velocity`` ``[..., 2]`` (its last step, metres)."""
    groups = [in_classes(present, g).any(-1) for g in CONTEXT_GROUPS]
    ids = agent_ids.to(present.device)
    lead, (nx, ny) = ids.shape[:-2], ids.shape[-2:]
    v = boxes.velocity.float().to(ids.device)  # on each agent's columns, 0 elsewhere
    velocity = slot_values(v, column_slots(ids, v.shape[-2])).view(*lead, nx, ny, 2).movedim(-1, -3).contiguous()
    footprint = _ego_footprint((nx, ny), ids.device)
    if footprint is not None:
        rows, cols, ego = footprint
        groups[VEHICLES][..., rows, cols] |= ego
        ego_motion = ego_velocity.to(ids.device, torch.float32).view(*lead, 2, 1, 1)
        velocity[..., rows, cols] = torch.where(ego, ego_motion, velocity[..., rows, cols])
    return torch.cat([torch.stack(groups, -3).float(), velocity], -3)


@made_once
def _ego_footprint(shape: tuple[int, int], device: torch.device) -> tuple[slice, slice, Tensor] | None:
    """:func:`~t3fast.data.classes.box_footprint` of the ego at the origin, its mask on ``device``."""
    footprint = box_footprint(0.0, 0.0, EGO_LENGTH, EGO_WIDTH, 0.0, shape)
    if footprint is None:
        return None
    rows, cols, inside = footprint
    return rows, cols, torch.from_numpy(inside).to(device)


def crop_context(context: Tensor, centre: Tensor, heading: Tensor) -> Tensor:
    """Each agent's view of the ``context`` ``[..., C, X, Y]`` (:func:`context_map`):
    ``[..., n, C, CROP[0], CROP[1]]``, rows ahead along its ``heading`` ``[..., n]`` from
    ``centre`` ``[..., n, 2]`` (metres, present frame), columns from its right to its left
    (symmetric about its centre line); the velocity channels turned into its frame."""
    lead, n = centre.shape[:-2], centre.shape[-2]
    cells = dict(dtype=torch.float32, device=context.device)
    along = -CROP_BEHIND + CROP_CELL * (torch.arange(CROP[0], **cells) + 0.5)
    across = CROP_CELL * (torch.arange(CROP[1], **cells) - (CROP[1] - 1) / 2)
    local = torch.stack(torch.meshgrid(along, across, indexing="ij"), -1)  # [A, W, 2]
    h = heading.float().to(context.device)[..., None, None]  # broadcast: one cosine and sine per agent
    points = rotate(local.expand(*lead, n, -1, -1, -1), h) + centre.float().to(context.device)[..., None, None, :]
    last = device_constant([s - 1 for s in context.shape[-2:]], torch.float32, context.device)
    cells = (points - device_constant(GRID_LOWER[:2], torch.float32, context.device)) / VOXEL_SIZE - 0.5
    grid = (cells / last * 2 - 1).flip(-1)  # grid_sample's x indexes the last dim (Y)
    # one image per window, its agents' crops stacked along the rows
    maps = context.reshape(-1, *context.shape[-3:])
    views = F.grid_sample(maps, grid.reshape(maps.shape[0], n * CROP[0], CROP[1], 2), mode="bilinear",
                          padding_mode="zeros", align_corners=True)
    views = views.view(*lead, context.shape[-3], n, *CROP).movedim(-3, -4)
    v = rotate(views[..., -2:, :, :].movedim(-3, -1), -h).movedim(-1, -3)
    return torch.cat([views[..., :-2, :, :], v], -3)


def mirror_views(views: Tensor) -> Tensor:
    """:func:`crop_context` views of the left-right mirrored agents (a training augmentation)."""
    out = views.flip(-1)
    return torch.cat([out[:, :-1], -out[:, -1:]], 1)


def mirror_kinematics(features: Tensor) -> Tensor:
    """:func:`kinematics` of the left-right mirrored agents (their lateral components negated)."""
    frames = (features.shape[1] - kinematic_features(1)) // 3 + 1
    lateral = {1, *range(4, 3 + 2 * (frames - 1), 2)}
    sign = [-1.0 if i in lateral else 1.0 for i in range(features.shape[1])]
    return features * device_constant(sign, features.dtype, features.device)


def corrected_motion(velocity: Tensor, heading: Tensor, correction: Tensor) -> tuple[Tensor, Tensor]:
    """The displacements ``[..., n, S, 2]`` (present frame, metres) and yaw changes ``[..., n, S]``
    of agents with fitted ``velocity`` ``[..., n, 2]`` (metres per step) and frame ``heading``
    ``[..., n]``: the constant velocity plus the :class:`~t3fast.models.box_motion.BoxMotionNet`
    ``correction`` ``[..., n, S, 3]``."""
    steps = correction.shape[-2]
    k = torch.arange(1, steps + 1, dtype=correction.dtype, device=correction.device)[:, None]
    local = k * rotate(velocity.to(correction.dtype), -heading.to(correction.dtype))[..., None, :] + correction[..., :2]
    heading = heading.to(correction.dtype)[..., None]
    return rotate(local, heading.expand(*heading.shape[:-1], steps)), correction[..., 2]


def future_poses(boxes: AgentBoxes, heading: Tensor, correction: Tensor) -> Tensor:
    """The boxes' poses ``[..., S, n, 3]`` (centre metres, yaw; present frame) at every future step:
    :func:`corrected_motion` from their fitted centre and yaw; an agent slower than
    :data:`STILL_STEP` stands at its present pose."""
    displacement, turn = corrected_motion(boxes.velocity, heading, correction.double())
    moving = (boxes.velocity.norm(dim=-1) >= STILL_STEP).to(displacement.dtype)
    centre = boxes.centre[..., None, :, :] + displacement.transpose(-3, -2) * moving[..., None, :, None]
    yaw = boxes.yaw[..., None, :] + turn.transpose(-2, -1) * moving[..., None, :]
    return torch.cat([centre, yaw[..., None]], -1)
