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

A frame's agents are records of ``n`` slots: on the CPU exactly the frame's agents (their count
read on the host, the per-agent sums over their columns alone); on a GPU (or under
:func:`~t3fast.host_syncs.sync_free`) :data:`AGENT_SLOTS` fixed slots, empty ones marked not
``valid``, the sums over every column: no host read, the same results. Fixed slots also let the
frames of every window of a batch go through in one call (records with leading dims ``[...]``),
so that a batch launches about as many kernels as one window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from t3fast import ops
from t3fast.data.classes import AGENT_CLASSES, GRID_LOWER, NUM_CLASSES, VOXEL_SIZE, in_classes
from t3fast.device_constants import device_constant
from t3fast.host_syncs import reads_host
from t3fast.models.ego_motion import transform_points

# metres an agent's centroid may move between two frames (0.5 s) to be matched: 16 m/s. At 4 m,
# 13 % of the moving agents' cells of training windows (the fast cars) had no velocity.
TRACK_GATE = 8.0
FOLLOW_GATE = 2.5  # metres between an agent's predicted and found centroid once its velocity is known
VELOCITY_CHANNELS = 4  # tracker_velocities: over the last step, and the chained mean over the last two
#: agents a frame's records hold where their count is not read on the host (a GPU run): the
#: components after the first AGENT_SLOTS (in the numbering of :func:`frame_agents`) are not
#: agents there (an Occ3D frame holds a few dozen)
AGENT_SLOTS = 256


def agent_slots(device: torch.device) -> int | None:
    """How many agents :func:`frame_agents` keeps on ``device``: None (the count read on the host:
    exactly the frame's agents) where the host is read (:func:`~t3fast.host_syncs.reads_host`),
    else :data:`AGENT_SLOTS`, so that nothing waits for the device."""
    return None if reads_host(device) else AGENT_SLOTS


def frame_agents(frame: Tensor, classes: Tensor | Sequence[int], slots: int | None = None) -> dict[str, Tensor]:
    """The agents of a frame ``[X, Y, Z]``: the connected BEV components of the columns holding an
    agent voxel (``classes``), in ``n`` slots: the frame's count (read on the host) with
    ``slots`` None, else ``slots`` (components beyond them are not agents; :func:`agent_slots`).
    With ``slots``, ``frame`` may have leading dims ``[..., X, Y, Z]`` (the frames of several
    windows at once), which every result but ``columns`` then has too.

    Returns:
        ``ids`` ``[X, Y]`` int64 (0 off the agents, else 1 + slot), ``mask`` ``[X, Y, Z]`` bool
        (the agents' voxels) and per slot: ``valid`` ``[n]`` (holds an agent), its majority class
        ``cls`` ``[n]`` (-1 where not valid), its ``votes`` ``[n, NUM_CLASSES]`` (voxels of each
        class) and its column centroid ``centroid`` ``[n, 2]`` (cells; 0 where not valid); and
        the ``columns`` ``[N, 2]`` (row-major) per-agent sums run over with their
        ``column_slot`` ``[N]``: the agents' columns, found on the host where it is read
        (:func:`~t3fast.host_syncs.reads_host`) for one frame, else every column, those off the
        agents in slot n.
    """
    is_agent = in_classes(frame, classes)
    lead, (nx, ny) = frame.shape[:-3], frame.shape[-3:-1]
    ids, count = ops.bev_components(is_agent.any(-1).reshape(-1, nx, ny))
    ids, count = ids.view(*lead, nx, ny), count.view(lead)
    if slots is None:
        if lead:
            raise ValueError(f"frame_agents: frames {list(frame.shape)} need fixed slots (one frame is [X, Y, Z])")
        slots = int(count)
        valid = torch.ones(slots, dtype=torch.bool, device=frame.device)
    else:
        ids = torch.where(ids > slots, 0, ids)
        is_agent &= (ids > 0)[..., None]
        valid = torch.arange(slots, device=frame.device) < count[..., None]
    if reads_host(frame.device) and not lead:  # the agents' columns, found on the host: a few percent of the frame
        columns = (ids > 0).nonzero()
        slot = ids[columns[:, 0], columns[:, 1]] - 1
    else:  # every column, those off the agents in slot n
        rows, cols = torch.arange(nx, device=frame.device), torch.arange(ny, device=frame.device)
        columns = torch.stack(torch.meshgrid(rows, cols, indexing="ij"), -1).reshape(-1, 2)
        slot = column_slots(ids, slots)
    cells = columns.double()
    size = slot_sums(torch.ones_like(cells[:, 0]).expand(slot.shape), slot, slots)
    centroid = slot_sums(cells.expand(*slot.shape, 2), slot, slots) / size.clamp(min=1)[..., None]
    votes = _class_votes(frame, ids, is_agent, slots)
    return dict(ids=ids, mask=is_agent, valid=valid, cls=torch.where(valid, votes.argmax(-1), -1), votes=votes,
                centroid=centroid, columns=columns, column_slot=slot)


def frame_of(agents: dict[str, Tensor], index: int, dim: int = 0) -> dict[str, Tensor]:
    """The agents of one frame of :func:`frame_agents` run on several: index ``index`` of their
    leading dim ``dim`` (views; ``columns``, shared by every frame, as it is)."""
    return {k: v if k == "columns" else v.select(dim, index) for k, v in agents.items()}


def slot_sums(values: Tensor, owner: Tensor, slots: int) -> Tensor:
    """Per slot, the sum of per-column ``values`` ``[..., N, *rest]`` over its columns (``owner``
    ``[..., N]``, a ``column_slot`` of :func:`frame_agents`; slot ``slots`` is dropped):
    ``[..., slots, *rest]``. One frame's sums run in column order, as its index_add does."""
    lead, rest = owner.shape[:-1], values.shape[owner.dim():]
    frames, flat = math.prod(lead), owner
    if lead:  # each frame's slots after the last frame's
        flat = (owner + torch.arange(frames, device=owner.device).view(*lead, 1) * (slots + 1)).flatten()
    sums = values.new_zeros(frames * (slots + 1), *rest).index_add_(0, flat, values.reshape(-1, *rest))
    return sums.view(*lead, slots + 1, *rest).narrow(len(lead), 0, slots)


def agent_levels(agents: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """Per slot of :func:`frame_agents`, the lowest level of its voxels and the one above its
    highest: ``bottom``, ``top`` ``[..., n]`` int64 (Z and 0 for an empty slot)."""
    mask, n = agents["mask"], agents["cls"].shape[-1]
    nz = mask.shape[-1]
    dtype = torch.uint8 if nz < 256 else torch.long  # the per-column maxima over a byte are 10x faster
    level = torch.arange(nz, device=mask.device, dtype=dtype)
    i, j = agents["columns"].unbind(1)
    lowest = nz - (mask * (nz - level)).amax(-1)[..., i, j].long()  # Z on a column without an agent voxel
    highest = (mask * (level + 1)).amax(-1)[..., i, j].long()
    slot = agents["column_slot"]
    lead = slot.shape[:-1]
    bottom = slot.new_full((*lead, n + 1), nz).scatter_reduce_(-1, slot, lowest, "amin")[..., :n]
    return bottom, slot.new_zeros(*lead, n + 1).scatter_reduce_(-1, slot, highest, "amax")[..., :n]


def column_slots(ids: Tensor, slots: int) -> Tensor:
    """Each column's slot ``[..., X * Y]`` (row-major; component map ``ids`` ``[..., X, Y]``), and
    ``slots`` (one past the last) off the agents: per-slot sums over the columns gather there,
    then are dropped."""
    return torch.where(ids > 0, ids - 1, slots).flatten(-2)


def slot_values(values: Tensor, column_slot: Tensor) -> Tensor:
    """Per column, its slot's row of ``values`` ``[..., n, *rest]``, and zeros for the columns off
    the agents (slot n, :func:`column_slots`): ``[..., N, *rest]`` for ``column_slot`` ``[..., N]``."""
    lead = column_slot.dim() - 1
    return _gather(torch.cat([values, values.new_zeros(*values.shape[:lead], 1, *values.shape[lead + 1:])], dim=lead),
                   column_slot)


def _class_votes(frame: Tensor, ids: Tensor, is_agent: Tensor, slots: int) -> Tensor:
    """Per slot, its voxels of each class ``[..., slots, NUM_CLASSES]`` int64: on the CPU from the
    agents' voxels of one frame (found on the host: a few percent of it), elsewhere from every
    voxel (nothing waits for the device)."""
    lead = frame.shape[:-3]
    if reads_host(frame.device) and not lead:
        votes = ids.new_zeros(slots + 1, NUM_CLASSES)
        ijz = is_agent.nonzero()
        label = frame[is_agent].long()
        votes.index_put_((ids[ijz[:, 0], ijz[:, 1]] - 1, label), torch.ones_like(label), accumulate=True)
        return votes[:slots]
    # each voxel votes in its column's row (the spare row `slots` off the agents) for its label,
    # or for the extra class NUM_CLASSES where it is no agent voxel: int32 keys made per column
    # and then in one pass over the voxels (the labels never index past their row)
    classes = NUM_CLASSES + 1
    row = torch.where(ids > 0, ids.int() - 1, slots)
    if lead:  # each frame's rows after the last frame's
        first = torch.arange(math.prod(lead), dtype=torch.int32, device=frame.device) * (slots + 1)
        row = row + first.view(*lead, 1, 1)
    key = (row * classes)[..., None] + torch.where(is_agent, frame, NUM_CLASSES)
    votes = ids.new_zeros(*lead, slots + 1, classes)
    one = torch.ones(1, dtype=torch.long, device=frame.device)
    votes.view(-1).index_add_(0, key.flatten(), one.expand(key.numel()))
    return votes[..., :slots, :NUM_CLASSES]


def match_components(present: dict[str, Tensor], previous: dict[str, Tensor], gate_cells: float) -> Tensor:
    """Per present slot (:func:`frame_agents`), the slot of the nearest valid previous component
    of its class whose centroid lies within ``gate_cells``, else -1: ``[..., n]`` int64."""
    n = present["cls"].shape[-1]
    if n == 0 or previous["cls"].shape[-1] == 0:
        return torch.full(present["cls"].shape, -1, dtype=torch.long, device=present["cls"].device)
    dist = (present["centroid"][..., :, None, :] - previous["centroid"][..., None, :, :]).norm(dim=-1)
    nearest, match = dist.masked_fill(_unmatchable(present["cls"], previous), math.inf).min(-1)
    return torch.where(nearest <= gate_cells, match, -1)


def _unmatchable(cls: Tensor, candidates: dict[str, Tensor]) -> Tensor:
    """``[..., n, m]``: which of the ``candidates``' slots (:func:`frame_agents`) an agent of class
    ``cls`` ``[..., n]`` can never be: those of another class, and the empty ones."""
    return (cls[..., :, None] != candidates["cls"][..., None, :]) | ~candidates["valid"][..., None, :]


def agent_velocities(present: dict[str, Tensor], previous: dict[str, Tensor], gate_cells: float) -> Tensor:
    """Per present slot, its velocity in cells per step ``[n, 2]``: the displacement of its
    centroid from the nearest previous component of its class (both in the present frame,
    :func:`match_components`); 0 without one within ``gate_cells``."""
    return _matched_steps(present, previous, match_components(present, previous, gate_cells))


def _gather(values: Tensor, index: Tensor) -> Tensor:
    """Per slot, ``values`` ``[..., m, *rest]`` at ``index`` ``[..., n]`` where ``index >= 0``,
    anything elsewhere (zeros if ``values`` is empty): a lookup that reads nothing on the host,
    for a ``torch.where`` on ``index >= 0``. ``[..., n, *rest]``."""
    lead = index.dim() - 1
    rest = values.shape[lead + 1:]
    if values.shape[lead] == 0:
        return values.new_zeros(*index.shape, *rest)
    if not lead:
        return values[index.clamp(min=0)]
    return torch.take_along_dim(values, index.clamp(min=0).view(*index.shape, *(1,) * len(rest)), dim=lead)


def _matched_steps(present: dict[str, Tensor], previous: dict[str, Tensor], match: Tensor) -> Tensor:
    """:func:`agent_velocities` for a given ``match`` (:func:`match_components`)."""
    found = (match >= 0)[..., None]
    return torch.where(found, present["centroid"] - _gather(previous["centroid"], match), 0.0)


def move_agents(frame: Tensor, agents: dict[str, Tensor], shift: Tensor, free: int,
                keep: Tensor | None = None) -> Tensor:
    """``frame`` ``[X, Y, Z]`` with its agents (:func:`frame_agents`) moved: per step ``s`` and
    slot ``c`` by ``shift[s, c]`` ``[S, n, 2]`` whole grid cells. The agents' voxels of the
    frame become ``free`` and each agent's voxels (whole columns, heights kept) are pasted at
    their shifted place, the agents ``keep`` ``[n]`` only (all when None); what leaves the grid
    is dropped, and where two land on one voxel the one later in row-major order wins. Returns
    ``[S, X, Y, Z]``. Where the host is not read, several windows' frames may come at once
    (leading dims ``[...]`` on every argument and the result)."""
    lead, (nx, ny, nz) = frame.shape[:-3], frame.shape[-3:]
    steps = shift.shape[-3]
    emptied = frame.masked_fill(agents["mask"], free)
    if agents["cls"].shape[-1] == 0:
        return emptied[..., None, :, :, :].expand(*lead, steps, nx, ny, nz).clone()
    slot = (agents["ids"] - 1).clamp(min=0)  # [X, Y]: each column's slot (0 off the agents, masked)
    paste = agents["mask"] if keep is None else agents["mask"] & _gather(keep, slot.flatten(-2)).view(slot.shape)[
        ..., None]
    if not reads_host(frame.device) or lead:
        return _paste_every_voxel(frame, paste, slot, shift, emptied)
    frames = emptied[None].expand(steps, nx, ny, nz).clone()
    ijz = paste.nonzero()
    moved = ijz[None, :, :2] + shift[:, slot[ijz[:, 0], ijz[:, 1]]]  # [S, V, 2]
    inside = (moved[..., 0] >= 0) & (moved[..., 0] < nx) & (moved[..., 1] >= 0) & (moved[..., 1] < ny)
    step = torch.arange(steps, device=ijz.device)[:, None].expand_as(inside)
    z = ijz[None, :, 2].expand_as(inside)
    frames[step[inside], moved[..., 0][inside], moved[..., 1][inside], z[inside]] = (
        frame[paste].to(frames.dtype).expand(steps, -1)[inside])
    return frames


def _paste_every_voxel(frame: Tensor, paste: Tensor, slot: Tensor, shift: Tensor, emptied: Tensor) -> Tensor:
    """:func:`move_agents` over every voxel at once, nothing read on the host (one window's frame
    ``[X, Y, Z]`` or several ``[..., X, Y, Z]``): the voxels ``paste`` of each column's ``slot``
    ``[..., X, Y]`` moved by its ``shift`` ``[..., S, n, 2]`` onto the frame with its agents
    removed, ``emptied``; ``[..., S, X, Y, Z]``. Each target voxel takes the label of the last
    source voxel landing on it: a voxel keeps its level, so among those the one of the last
    column, which one ``amax`` over each voxel's key (its column, then its label in the low 8
    bits) finds, scattered by columns."""
    lead, (nx, ny, nz) = frame.shape[:-3], frame.shape[-3:]
    steps, columns = shift.shape[-3], nx * ny
    device = frame.device
    d = torch.take_along_dim(shift, slot.flatten(-2)[..., None, :, None], dim=-2).view(*lead, steps, nx, ny, 2)
    i = torch.arange(nx, device=device)[:, None] + d[..., 0]
    j = torch.arange(ny, device=device)[None, :] + d[..., 1]
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)  # [..., S, X, Y]
    target = torch.where(inside, i * ny + j, columns).flatten(-2)  # a column beyond the grid: the spare one
    order = torch.arange(columns, dtype=torch.int32, device=device).view(nx, ny, 1) * 256
    key = torch.where(paste, order + frame.int(), -1).flatten(-3, -2)[..., None, :, :]  # [..., 1, X * Y, Z]
    winner = torch.full((*lead, steps, columns + 1, nz), -1, dtype=torch.int32, device=device)
    winner.scatter_reduce_(-2, target[..., None].expand(*target.shape, nz), key.expand(*lead, steps, columns, nz),
                           "amax")
    winner = winner[..., :columns, :].unflatten(-2, (nx, ny))
    labels = winner.to(torch.uint8).to(emptied.dtype)  # the cast to uint8 keeps the low 8 bits: the label
    return torch.where(winner >= 0, labels, emptied[..., None, :, :, :])


def component_shifts(agents: dict[str, Tensor], displacement: Tensor) -> Tensor:
    """Per step and agent slot of :func:`frame_agents`, the mean of a per-plane-cell forward
    ``displacement`` ``[..., S, 2, H, W]`` (plane cells) over the agent's grid columns, in grid
    cells: ``[..., S, n, 2]`` float64 (0 for an empty slot). An agent moves as a whole (a car
    does not stretch)."""
    nx, ny = agents["ids"].shape[-2:]
    h, w = displacement.shape[-2:]
    fx, fy = -(-nx // h), -(-ny // w)
    n = agents["cls"].shape[-1]
    slot, columns = agents["column_slot"], agents["columns"]
    per_column = displacement[..., columns[:, 0] // fx, columns[:, 1] // fy].double().movedim(-1, -3)  # [..., N, S, 2]
    total = slot_sums(per_column, slot, n)
    count = slot_sums(torch.ones_like(per_column[..., 0, 0]), slot, n).clamp(min=1)
    scale = device_constant((fx, fy), total.dtype, total.device)
    return (total / count[..., None, None] * scale).transpose(-3, -2)


def chained_velocities(present: dict[str, Tensor], previous: dict[str, Tensor], older: dict[str, Tensor],
                       gate_cells: float) -> Tensor:
    """Per present slot, its mean velocity over the last two steps ``[n, 2]`` (cells per step)
    along the matched chain present -> previous -> older (each link :func:`match_components`);
    where the chain breaks, the last step's velocity (:func:`agent_velocities`). Following the
    chain, rather than matching the present against the older frame directly, keeps a queued
    car from taking the place of the one ahead."""
    match = match_components(present, previous, gate_cells)
    velocity = _matched_steps(present, previous, match)
    back = torch.where(match >= 0, _gather(match_components(previous, older, gate_cells), match), -1)
    two_steps = (present["centroid"] - _gather(older["centroid"], back)) / 2
    return torch.where((back >= 0)[..., None], two_steps, velocity)


def column_values(ids: Tensor, values: Tensor) -> Tensor:
    """Per-slot ``values`` ``[..., n, C]`` of the component map ``ids`` ``[..., X, Y]``
    (:func:`frame_agents`) on its grid columns, and whether a column holds an agent (the last
    channel): ``[..., C + 1, X, Y]`` float32."""
    *lead, nx, ny = ids.shape
    per_column = slot_values(values, column_slots(ids, values.shape[-2])).transpose(-1, -2)
    return torch.cat([per_column.reshape(*lead, -1, nx, ny).float(), (ids > 0).float()[..., None, :, :]], -3)


def _pooled_field(columns: Tensor, plane_shape: tuple[int, int]) -> Tensor:
    """Per-component values on the grid columns (:func:`column_values` ``[B, C + 1, X, Y]``, in
    grid cells per step) as a field on the xy plane: ``[B, C, H, W]`` float32 in plane cells (see
    :func:`agent_velocity_field`)."""
    nx, ny = columns.shape[-2:]
    h, w = plane_shape
    fx, fy = -(-nx // h), -(-ny // w)  # grid columns per plane cell (an odd grid's last cell has fewer)
    c = columns.shape[1] - 1
    pooled = F.avg_pool2d(F.pad(columns, (0, fy * w - ny, 0, fx * h - nx)), (fx, fy))
    count, agent = pooled[:, -1:], pooled[:, -1:] > 0
    field = pooled[:, :-1] / count.clamp(min=1e-6)  # 0 where no agent column
    ring = F.avg_pool2d(torch.cat([field, agent.float()], 1), 3, stride=1, padding=1, count_include_pad=False)
    grown = ring[:, :-1] / ring[:, -1:].clamp(min=1e-6)  # 0 where no agent is near
    field = torch.where(agent, field, grown)
    return field / device_constant([fx, fy] * (c // 2), field.dtype, field.device).view(1, -1, 1, 1)


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
    slots = agent_slots(present.device)
    columns = []
    for n in range(present.shape[0]):
        now = frame_agents(present[n], classes, slots)
        velocity = agent_velocities(now, frame_agents(previous[n], classes, slots), gate / VOXEL_SIZE)
        columns.append(column_values(now["ids"], velocity))
    return _pooled_field(torch.stack(columns), plane_shape)


def tracker_velocities(frames: Tensor, plane_shape: tuple[int, int], gate: float = TRACK_GATE) -> Tensor:
    """What the flow forecaster starts from: ``frames`` ``[B, 3, X, Y, Z]``, the last three
    observed frames moved into the present one (the present last) -> ``[B, 4, H, W]``: the
    agents' velocities over the last step (channels 0-1, what the tracker moves them with) and
    their mean velocity over the last two steps along the matched chain (channels 2-3,
    :func:`chained_velocities`: less noisy, and with the first it shows acceleration), each
    pooled as :func:`agent_velocity_field`."""
    if frames.dim() != 5 or frames.shape[1] != 3:
        raise ValueError(f"tracker_velocities: frames must be [B, 3, X, Y, Z], got {list(frames.shape)}")
    gate_cells = gate / VOXEL_SIZE
    slots = agent_slots(frames.device)
    if slots is None:  # each window's agents counted on the host
        windows = [[frame_agents(frames[n, t], AGENT_CLASSES) for t in range(3)] for n in range(frames.shape[0])]
    else:  # every window's frames at once
        every = frame_agents(frames, AGENT_CLASSES, slots)
        windows = [[frame_of(every, t, 1) for t in range(3)]]
    columns = []
    for older, previous, now in windows:
        velocity = torch.cat([agent_velocities(now, previous, gate_cells),
                              chained_velocities(now, previous, older, gate_cells)], dim=-1)
        columns.append(column_values(now["ids"], velocity))
    return _pooled_field(torch.stack(columns) if slots is None else columns[0], plane_shape)


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
    lower = device_constant(GRID_LOWER[:2], cells.dtype, cells.device)
    local = lower + (cells + 0.5) * VOXEL_SIZE
    return transform_points(pose, local)


def follow_agents(agents: list[dict[str, Tensor]], poses: Tensor) -> Tensor:
    """Per present slot (the last of ``agents``, :func:`frame_agents` of each frame), the slot of
    its agent in every frame, following it back from the present: ``[n, T]`` int64, -1 where
    it was lost (and in every frame before; and for an empty slot). The first step back
    searches the tracker's gate, the next ones ``FOLLOW_GATE`` around the position its
    velocity predicts. Frames of several windows at once (records with leading dims ``[...]``,
    ``poses`` ``[..., T, 3]``) give ``[..., n, T]``."""
    now = agents[-1]
    lead, n, frames = now["cls"].shape[:-1], now["cls"].shape[-1], len(agents)
    device = now["centroid"].device
    match = torch.full((*lead, n, frames), -1, dtype=torch.long, device=device)
    match[..., -1] = torch.where(now["valid"], torch.arange(n, device=device), -1)
    position = cell_metres(now["centroid"], poses[..., -1:, :])
    velocity = torch.zeros_like(position)
    gate = torch.full((*lead, n), TRACK_GATE, dtype=torch.float64, device=device)
    alive = now["valid"].clone()
    for t in range(frames - 2, -1, -1):
        before = agents[t]
        if before["cls"].shape[-1] == 0:
            break
        found = cell_metres(before["centroid"], poses[..., t : t + 1, :])
        dist = (position - velocity)[..., :, None, :].sub(found[..., None, :, :]).norm(dim=-1)
        nearest, index = dist.masked_fill(_unmatchable(now["cls"], before), math.inf).min(-1)
        ok = alive & (nearest <= gate)
        match[..., t] = torch.where(ok, index, match[..., t])
        there = torch.take_along_dim(found, index[..., None], dim=-2)
        velocity = torch.where(ok[..., None], position - there, velocity)
        position = torch.where(ok[..., None], there, position)
        gate = torch.where(ok, FOLLOW_GATE, gate)
        alive &= ok
    return match
