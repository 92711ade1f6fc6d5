"""The classical tracker: the agents of a frame, their matches in earlier frames, their velocities.

In the ego-aligned frame (the previous frame moved into the present one with the past poses),
the columns holding an agent voxel (vehicles and humans) form 8-connected BEV components, each
with its majority class (:func:`frame_agents`). Two ways of matching them back in time:

* centroid matching (:func:`match_components`, :func:`agent_velocities`,
  :func:`chained_velocities`): a present component's velocity is the displacement of its
  centroid from the nearest previous component of its class within a gate. This is what the
  tracker baselines move agents with (:mod:`t3fast.evaluation.baselines`), and what the flow
  forecaster starts from (:func:`tracker_velocities`): it learns a correction to it rather than
  finding every agent's motion from scratch;
* following (:func:`follow_agents`): each present agent followed back through every past frame
  (in metres, each frame taken into the present one with its pose), searching around where its
  last velocity puts it: the tracks the fitted boxes (:mod:`t3fast.agents.boxes`) are fitted to.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from t3fast import ops
from t3fast.data.classes import AGENT_CLASSES, GRID_LOWER, NUM_CLASSES, VOXEL_SIZE, in_classes
from t3fast.models.ego_motion import compose

# metres an agent's centroid may move between two frames (0.5 s) to be matched: 16 m/s. At 4 m,
# 13 % of the moving agents' cells of training windows (the fast cars) had no velocity.
TRACK_GATE = 8.0
FOLLOW_GATE = 2.5  # metres between an agent's predicted and found centroid once its velocity is known
VELOCITY_CHANNELS = 4  # tracker_velocities: over the last step, and the chained mean over the last two


def bev_components(mask: Tensor) -> tuple[Tensor, int]:
    """8-connected components of a BEV mask ``[X, Y]`` (bool): labels int64 ``[X, Y]``, 0 off the
    mask and 1..n on it, and n (:func:`t3fast.ops.bev_components`; reading n is the one host
    synchronisation)."""
    ids, n = ops.bev_components(mask[None])
    return ids[0], int(n[0])


def frame_agents(frame: Tensor, classes: Tensor) -> dict[str, Tensor]:
    """The agents of a frame ``[X, Y, Z]``: their voxels (``ijz`` ``[V, 3]``, ``label`` ``[V]``,
    ``component`` ``[V]`` 0-based), the component map ``ids`` ``[X, Y]`` (0 off the agents, else
    1 + component) and, per connected BEV component of the columns holding an agent voxel, its
    majority class ``cls`` ``[n]`` and column centroid ``centroid`` ``[n, 2]`` (cells)."""
    is_agent = in_classes(frame, classes)
    ids, n = bev_components(is_agent.any(-1))
    ijz = is_agent.nonzero()
    label = frame[is_agent].long()
    component = ids[ijz[:, 0], ijz[:, 1]] - 1
    votes = torch.zeros(n, NUM_CLASSES, dtype=torch.long, device=frame.device)
    votes.index_put_((component, label), torch.ones_like(label), accumulate=True)
    cols = (ids > 0).nonzero()
    col_id = ids[cols[:, 0], cols[:, 1]] - 1
    size = torch.bincount(col_id, minlength=n).double()
    centroid = torch.stack([torch.bincount(col_id, cols[:, a].double(), minlength=n) for a in (0, 1)], -1)
    return dict(ijz=ijz, label=label, component=component, ids=ids, cls=votes.argmax(1),
                centroid=centroid / size.clamp(min=1)[:, None], mask=is_agent)


def match_components(present: dict[str, Tensor], previous: dict[str, Tensor], gate_cells: float) -> Tensor:
    """Per present component (:func:`frame_agents`), the index of the nearest previous component
    of its class whose centroid lies within ``gate_cells``, else -1: ``[n]`` int64."""
    n = present["cls"].shape[0]
    if n == 0 or previous["cls"].shape[0] == 0:
        return torch.full((n,), -1, dtype=torch.long, device=present["cls"].device)
    dist = (present["centroid"][:, None] - previous["centroid"][None]).norm(dim=-1)
    dist = dist.masked_fill(present["cls"][:, None] != previous["cls"][None], math.inf)
    nearest, match = dist.min(1)
    return torch.where(nearest <= gate_cells, match, torch.full_like(match, -1))


def agent_velocities(present: dict[str, Tensor], previous: dict[str, Tensor], gate_cells: float) -> Tensor:
    """Per present component, its velocity in cells per step ``[n, 2]``: the displacement of its
    centroid from the nearest previous component of its class (both in the present frame,
    :func:`match_components`); 0 without one within ``gate_cells``."""
    return _matched_steps(present, previous, match_components(present, previous, gate_cells))


def _matched_steps(present: dict[str, Tensor], previous: dict[str, Tensor], match: Tensor) -> Tensor:
    """:func:`agent_velocities` for a given ``match`` (:func:`match_components`)."""
    velocity = torch.zeros(match.shape[0], 2, dtype=torch.float64, device=match.device)
    found = match >= 0
    velocity[found] = present["centroid"][found] - previous["centroid"][match[found]]
    return velocity


def move_agents(frame: Tensor, agents: dict[str, Tensor], shift: Tensor, free: int) -> Tensor:
    """``frame`` ``[X, Y, Z]`` with its agents (:func:`frame_agents`) moved: per step ``s`` and
    component ``c`` by ``shift[s, c]`` ``[S, n, 2]`` whole grid cells. The agents' voxels of the
    frame become ``free`` and each component's voxels (whole columns, heights kept) are pasted
    at their shifted place; what leaves the grid is dropped. Returns ``[S, X, Y, Z]``."""
    nx, ny, nz = frame.shape
    steps = shift.shape[0]
    frames = frame.masked_fill(agents["mask"], free).expand(steps, nx, ny, nz).clone()
    ijz = agents["ijz"]
    if ijz.shape[0]:
        moved = ijz[None, :, :2] + shift[:, agents["component"]]  # [S, V, 2]
        inside = (moved[..., 0] >= 0) & (moved[..., 0] < nx) & (moved[..., 1] >= 0) & (moved[..., 1] < ny)
        step = torch.arange(steps, device=ijz.device)[:, None].expand_as(inside)
        z = ijz[None, :, 2].expand_as(inside)
        frames[step[inside], moved[..., 0][inside], moved[..., 1][inside], z[inside]] = (
            agents["label"].to(frames.dtype).expand(steps, -1)[inside])
    return frames


def component_shifts(agents: dict[str, Tensor], displacement: Tensor) -> Tensor:
    """Per step and agent component of :func:`frame_agents`, the mean of a per-plane-cell
    forward ``displacement`` ``[S, 2, H, W]`` (plane cells) over the component's grid columns,
    in grid cells: ``[S, n, 2]`` float. A component moves as a whole (a car does not stretch)."""
    ids = agents["ids"]
    nx, ny = ids.shape
    h, w = displacement.shape[-2:]
    fx, fy = -(-nx // h), -(-ny // w)
    cols = (ids > 0).nonzero()
    n = agents["cls"].shape[0]
    component = ids[cols[:, 0], cols[:, 1]] - 1
    per_column = displacement[:, :, cols[:, 0] // fx, cols[:, 1] // fy].double()  # [S, 2, N]
    total = per_column.new_zeros(displacement.shape[0], 2, n).index_add_(2, component, per_column)
    count = torch.bincount(component, minlength=n).clamp(min=1).double()
    scale = total.new_tensor([fx, fy]).view(1, 2, 1)
    return (total / count * scale).transpose(1, 2)


def chained_velocities(present: dict[str, Tensor], previous: dict[str, Tensor], older: dict[str, Tensor],
                       gate_cells: float) -> Tensor:
    """Per present component, its mean velocity over the last two steps ``[n, 2]`` (cells per
    step) along the matched chain present -> previous -> older (each link
    :func:`match_components`); where the chain breaks, the last step's velocity
    (:func:`agent_velocities`). Following the chain, rather than matching the present against
    the older frame directly, keeps a queued car from taking the place of the one ahead."""
    match = match_components(present, previous, gate_cells)
    velocity = _matched_steps(present, previous, match)
    back = torch.full_like(match, -1)
    found = match >= 0
    back[found] = match_components(previous, older, gate_cells)[match[found]]
    chained = back >= 0
    velocity[chained] = (present["centroid"][chained] - older["centroid"][back[chained]]) / 2
    return velocity


def _pooled_field(shape: tuple[int, int], agents: list[tuple[Tensor, Tensor]], plane_shape: tuple[int, int],
                  channels: int, device: torch.device) -> Tensor:
    """Per-component values as a field on the xy plane: ``agents`` holds per window the component
    map ``ids`` ``[X, Y]`` (:func:`frame_agents`) and values ``[n, channels]`` in grid cells per step ->
    ``[B, C, H, W]`` float32 in plane cells (see :func:`agent_velocity_field`)."""
    nx, ny = shape
    h, w = plane_shape
    fx, fy = -(-nx // h), -(-ny // w)  # grid columns per plane cell (an odd grid's last cell has fewer)
    c = channels
    # per grid column: the values and whether it holds an agent
    columns = torch.zeros(len(agents), c + 1, nx, ny, dtype=torch.float32, device=device)
    for n, (ids, values) in enumerate(agents):
        on = ids > 0
        columns[n, -1] = on.float()
        columns[n, :c, on] = values[ids[on] - 1].T.float()
    pooled = F.avg_pool2d(F.pad(columns, (0, fy * w - ny, 0, fx * h - nx)), (fx, fy))
    count, agent = pooled[:, -1:], pooled[:, -1:] > 0
    field = pooled[:, :-1] / count.clamp(min=1e-6)  # 0 where no agent column
    ring = F.avg_pool2d(torch.cat([field, agent.float()], 1), 3, stride=1, padding=1, count_include_pad=False)
    grown = ring[:, :-1] / ring[:, -1:].clamp(min=1e-6)  # 0 where no agent is near
    field = torch.where(agent, field, grown)
    return field / torch.tensor([fx, fy] * (c // 2), device=field.device, dtype=field.dtype).view(1, -1, 1, 1)


def agent_velocity_field(
    present: Tensor, previous: Tensor, plane_shape: tuple[int, int], gate: float = TRACK_GATE,
    classes: tuple[int, ...] = AGENT_CLASSES,
) -> Tensor:
    """The tracker's agent velocities as a field on the xy plane.

    Args:
        present: labels ``[B, X, Y, Z]`` of the present frame.
        previous: labels ``[B, X, Y, Z]`` of the frame before, moved into the present frame.
        plane_shape: ``(H, W)`` of the xy plane, ``ceil(X / H)`` grid columns per cell along x
            (likewise y).
        gate: metres a centroid may move between the frames to be matched.
    Returns:
        ``[B, 2, H, W]`` float32: at each plane cell holding an agent column, the mean velocity
        of those columns in plane cells per 0.5 s step (along H, along W); the ring of cells
        around an agent takes the mean of its agent neighbours (the latent of an agent spreads
        a little beyond its voxels); 0 elsewhere.
    """
    if previous.shape != present.shape:
        raise ValueError(f"agent_velocity_field: previous {list(previous.shape)} and present "
                         f"{list(present.shape)} differ in shape")
    wanted = torch.tensor(classes, dtype=present.dtype, device=present.device)
    agents = []
    for n in range(present.shape[0]):
        now = frame_agents(present[n], wanted)
        agents.append((now["ids"], agent_velocities(now, frame_agents(previous[n], wanted), gate / VOXEL_SIZE)))
    return _pooled_field(tuple(present.shape[1:3]), agents, plane_shape, 2, present.device)


def tracker_velocities(frames: Tensor, plane_shape: tuple[int, int], gate: float = TRACK_GATE) -> Tensor:
    """What the flow forecaster starts from: ``frames`` ``[B, 3, X, Y, Z]``, the last three
    observed frames moved into the present one (the present last) -> ``[B, 4, H, W]``: the
    agents' velocities over the last step (channels 0-1, what the tracker moves them with) and
    their mean velocity over the last two steps along the matched chain (channels 2-3,
    :func:`chained_velocities`: less noisy, and with the first it shows acceleration), each
    pooled as :func:`agent_velocity_field`."""
    if frames.dim() != 5 or frames.shape[1] != 3:
        raise ValueError(f"tracker_velocities: frames must be [B, 3, X, Y, Z], got {list(frames.shape)}")
    wanted = torch.tensor(AGENT_CLASSES, dtype=frames.dtype, device=frames.device)
    gate_cells = gate / VOXEL_SIZE
    agents = []
    for n in range(frames.shape[0]):
        older, previous, now = (frame_agents(frames[n, t], wanted) for t in range(3))
        velocity = torch.cat([agent_velocities(now, previous, gate_cells),
                              chained_velocities(now, previous, older, gate_cells)], dim=1)
        agents.append((now["ids"], velocity))
    return _pooled_field(tuple(frames.shape[2:4]), agents, plane_shape, VELOCITY_CHANNELS, frames.device)


def blended_velocity(velocity: Tensor) -> Tensor:
    """The velocity the flow forecaster moves agents with before its learnt correction, from
    :func:`tracker_velocities` ``[B, 4, H, W]`` -> ``[B, 2, H, W]``: the mean of the last step's
    velocity and the chained two-step mean. On held-out windows this moved agents better than
    the last step alone (label-space render at true poses, 40 test windows: moving-class mIoU
    36.9 vs 35.8; 40 val windows: 34.4 vs 32.3; ``benchmarks/tools/motion_ceilings.py``)."""
    return (velocity[:, :2] + velocity[:, 2:4]) / 2


def cell_metres(cells: Tensor, pose: Tensor) -> Tensor:
    """Continuous cell coordinates ``[..., 2]`` of a frame with planar ``pose`` (in the present
    frame) -> metres in the present frame."""
    lower = cells.new_tensor(GRID_LOWER[:2])
    local = lower + (cells + 0.5) * VOXEL_SIZE
    return compose(pose.expand(*local.shape[:-1], 3), torch.cat([local, torch.zeros_like(local[..., :1])], -1))[..., :2]


def follow_agents(agents: list[dict[str, Tensor]], poses: Tensor) -> Tensor:
    """Per present component (the last of ``agents``, :func:`frame_agents` of each frame), the
    index of its component in every frame, following it back from the present: ``[n, T]``
    int64, -1 where it was lost (and in every frame before). The first step back searches the
    tracker's gate, the next ones ``FOLLOW_GATE`` around the position its velocity predicts."""
    now = agents[-1]
    n, frames = now["cls"].shape[0], len(agents)
    device = now["centroid"].device
    match = torch.full((n, frames), -1, dtype=torch.long, device=device)
    match[:, -1] = torch.arange(n, device=device)
    position = cell_metres(now["centroid"], poses[-1])
    velocity = torch.zeros_like(position)
    gate = torch.full((n,), TRACK_GATE, dtype=torch.float64, device=device)
    alive = torch.ones(n, dtype=torch.bool, device=device)
    for t in range(frames - 2, -1, -1):
        before = agents[t]
        if before["cls"].shape[0] == 0:
            break
        found = cell_metres(before["centroid"], poses[t])
        dist = (position - velocity)[:, None].sub(found[None]).norm(dim=-1)
        dist = dist.masked_fill(now["cls"][:, None] != before["cls"][None], math.inf)
        nearest, index = dist.min(1)
        ok = alive & (nearest <= gate)
        match[ok, t] = index[ok]
        velocity = torch.where(ok[:, None], position - found[index], velocity)
        position = torch.where(ok[:, None], found[index], position)
        gate = torch.where(ok, torch.full_like(gate, FOLLOW_GATE), gate)
        alive &= ok
    return match
