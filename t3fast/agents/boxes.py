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
footprint's edge, sharpened over the iterations) fitted by Adam on its closed-form gradient
(no autograd), all agents of a window at once.
An agent is drawn as a box only where the fit explains its columns (IoU >= ``MIN_FIT_IOU``), it
is of one class and it was seen in two frames or more; queued cars merged into one component
or a truck with its trailer are not boxes, and move as voxels.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.nn import functional as F

from t3fast import ops
from t3fast.agents.tracker import cell_metres, follow_agents, frame_agents
from t3fast.data.classes import AGENT_CLASSES, GRID_LOWER, NUM_CLASSES, VOXEL_SIZE

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
    """Fitted boxes of one frame's agents (per component of :func:`frame_agents`, ``n`` of them),
    in the present frame, metres: ``centre`` ``[n, 2]``, ``velocity`` ``[n, 2]`` per step (the present one),
    ``yaw`` ``[n]``, ``length``, ``width`` ``[n]``; ``bottom``, ``top`` ``[n]`` the levels the
    agent's voxels span (top exclusive); ``label`` ``[n]`` its class; ``drawn`` ``[n]`` bool:
    the fit is trusted and the agent is drawn as this box; ``track`` ``[n, T, 2]`` the agent's
    column centroid in each observed frame (present frame, metres; NaN where it was not found);
    ``future`` ``[S, n, 3]`` where a learned motion (:mod:`t3fast.models.box_motion`) placed each
    box at every future step (centre, yaw; present frame), None to move them by their fitted
    velocity."""

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


def _samples(agents: list[dict[str, Tensor]], match: Tensor, poses: Tensor, reach: Tensor) -> dict[str, Tensor]:
    """The columns that decide each agent's box: in every frame where it was found, those within
    ``reach`` cells of its centroid and ``NEAR`` cells of one of its columns (the far ones say
    nothing once the box is near). Flat over agents and frames: ``position`` ``[N, 2]`` (present
    frame, metres), ``owned`` ``[N]`` (one of the agent's columns), ``agent`` ``[N]`` and
    ``time`` ``[N]`` (frames before the present, <= 0)."""
    half = int(reach.max().ceil())
    side = torch.arange(-half, half + 1, device=reach.device)
    offsets = torch.stack(torch.meshgrid(side, side, indexing="ij"), -1).reshape(-1, 2)
    within = offsets.double().norm(dim=-1)[None] <= reach[:, None]  # [n, P]
    frames, n = len(agents), match.shape[0]
    out: dict[str, list[Tensor]] = {"position": [], "owned": [], "agent": [], "time": []}
    for t, frame in enumerate(agents):
        index = match[:, t]
        seen = index >= 0
        if not bool(seen.any()):
            continue
        nx, ny = frame["ids"].shape
        centroid = reach.new_zeros(n, 2)
        centroid[seen] = frame["centroid"][index[seen]]
        cells = centroid.round().long()[:, None] + offsets[None]
        inside = (cells[..., 0] >= 0) & (cells[..., 0] < nx) & (cells[..., 1] >= 0) & (cells[..., 1] < ny)
        cells = torch.stack([cells[..., 0].clamp(0, nx - 1), cells[..., 1].clamp(0, ny - 1)], -1)
        owned = (frame["ids"][cells[..., 0], cells[..., 1]] == index[:, None] + 1) & inside
        side = 2 * half + 1
        near = F.max_pool2d(owned.view(n, 1, side, side).float(), 2 * NEAR + 1, 1, NEAR).view(n, -1) > 0
        keep = (inside & within & near & seen[:, None]).nonzero()
        out["position"].append(cell_metres(cells[keep[:, 0], keep[:, 1]].double(), poses[t]))
        out["owned"].append(owned[keep[:, 0], keep[:, 1]].double())
        out["agent"].append(keep[:, 0])
        out["time"].append(reach.new_full((keep.shape[0],), float(t - (frames - 1))))
    return {k: torch.cat(v) for k, v in out.items()}


@dataclass
class FitSamples:
    """:func:`_samples` as the fit reads them, float32 around each agent's starting centre:
    ``points`` ``[N, 2]`` (metres), ``time`` ``[N]`` (steps, <= 0), ``agent`` ``[N]`` int64,
    ``owned`` ``[N]`` (1: one of the agent's columns), ``count`` the loss's normaliser."""

    points: Tensor
    time: Tensor
    agent: Tensor
    owned: Tensor
    count: int


@contextmanager
def _one_thread() -> Iterator[None]:
    """Run on one intra-op thread: the fit is hundreds of small ops, and on two hyperthreads
    each one's fork-join cost more than the op (a window: 0.4 s on one thread, 1.4 s on two)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def fit_loss(params: Tensor, samples: FitSamples, softness: float) -> Tensor:
    """The objective the box fit descends (float, differentiable; the fit itself uses its
    closed-form gradient, :func:`fit_gradient`): the summed logistic loss of the soft
    inside/outside (signed footprint distance over ``softness`` metres) against each sample's
    ownership, over the samples' count, plus the zero-acceleration prior. ``params`` ``[n, 9]``:
    centre, velocity per step, yaw, log length, log width, acceleration per step^2."""
    margin = _margins(params, samples)[0]
    loss = F.binary_cross_entropy_with_logits(margin / softness, samples.owned, reduction="sum")
    return loss / samples.count + ACCEL_PRIOR * params[:, 7:9].pow(2).sum() / params.shape[0]


def _margins(params: Tensor, samples: FitSamples) -> tuple[Tensor, ...]:
    """(the footprint margin ``[N]`` of every sample, and the terms its gradient reads)."""
    box = params.index_select(0, samples.agent)
    time = samples.time[:, None]
    centre = box[:, :2] + box[:, 2:4] * time + 0.5 * box[:, 7:9] * time * time
    d = samples.points - centre
    c, s = torch.cos(box[:, 4]), torch.sin(box[:, 4])
    along = c * d[:, 0] + s * d[:, 1]
    across = -s * d[:, 0] + c * d[:, 1]
    half_length, half_width = box[:, 5].exp() / 2, box[:, 6].exp() / 2
    by_length, by_width = half_length - along.abs(), half_width - across.abs()
    return torch.minimum(by_length, by_width), by_length, by_width, along, across, c, s, half_length, half_width


def fit_gradient(params: Tensor, samples: FitSamples, softness: float) -> Tensor:
    """The gradient ``[n, 9]`` of :func:`fit_loss` with respect to ``params``, in closed form
    (no autograd: the fit runs at inference, batched, on any device). Where the footprint's
    two distances tie, each takes half, as ``torch.minimum``'s gradient does."""
    margin, by_length, by_width, along, across, c, s, half_length, half_width = _margins(params, samples)
    g = (torch.sigmoid(margin / softness) - samples.owned) / (softness * samples.count)  # d loss / d margin
    share = torch.where(by_length < by_width, 1.0, torch.where(by_length == by_width, 0.5, 0.0))
    g_length, g_width = g * share, g * (1 - share)
    g_along, g_across = -g_length * along.sign(), -g_width * across.sign()
    g_x = -(g_along * c - g_across * s)  # d loss / d centre (the point minus the centre is d)
    g_y = -(g_along * s + g_across * c)
    time = samples.time
    half_t2 = 0.5 * time * time
    rows = torch.stack([g_x, g_y, g_x * time, g_y * time, g_along * across - g_across * along,
                        g_length * half_length, g_width * half_width, g_x * half_t2, g_y * half_t2], 1)
    grad = params.new_zeros(params.shape).index_add_(0, samples.agent, rows)
    grad[:, 7:9] += 2 * ACCEL_PRIOR / params.shape[0] * params[:, 7:9]
    return grad


def _optimise(start: Tensor, found: dict[str, Tensor], iters: int) -> tuple[Tensor, Tensor]:
    """Boxes ``[n, 7]`` (centre, velocity per step, yaw, log length, log width; the velocity the
    present one of a constant acceleration fitted with them) fitted from ``start`` to the
    :func:`_samples` ``found``, and each one's footprint IoU with its columns over the frames
    ``[n]``: ``iters`` Adam steps (learning rate ``FIT_LR``) on :func:`fit_gradient`, the
    softness narrowing from ``SOFTNESS[0]`` to ``SOFTNESS[1]``. Fitted in float32 around each
    agent's starting centre (centimetres need no more), which halves the cost of the sines and
    cosines."""
    agent = found["agent"]
    samples = FitSamples((found["position"] - start[agent, :2]).float(), found["time"].float(), agent,
                         found["owned"].float(), max(agent.numel(), 1))
    offset = start.clone()
    offset[:, 2:] = 0
    n = start.shape[0]
    params = torch.cat([(start - offset).float(), start.new_zeros(n, 2, dtype=torch.float32)], 1)
    mean, square = torch.zeros_like(params), torch.zeros_like(params)
    beta1, beta2 = 0.9, 0.999  # Adam's defaults
    with _one_thread():
        for it in range(iters):
            softness = SOFTNESS[0] * (SOFTNESS[1] / SOFTNESS[0]) ** (it / max(iters - 1, 1))
            grad = fit_gradient(params, samples, softness)
            mean.lerp_(grad, 1 - beta1)
            square.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            denom = (square.sqrt() / math.sqrt(1 - beta2 ** (it + 1))).add_(1e-8)
            params.addcdiv_(mean, denom, value=-FIT_LR / (1 - beta1 ** (it + 1)))
        inside = (_margins(params, samples)[0] > 0).float()
    owned = samples.owned
    both = owned.new_zeros(n).index_add_(0, agent, inside * owned)
    either = owned.new_zeros(n).index_add_(0, agent, (inside + owned).clamp(max=1))
    return params[:, :7].double() + offset, (both / either.clamp(min=1)).double()


def fit_agent_boxes(frames: Tensor, poses: Tensor, iters: int = FIT_ITERS) -> tuple[dict[str, Tensor], AgentBoxes]:
    """Boxes of the present frame's agents fitted to their columns in every observed frame.

    Args:
        frames: labels ``[T, X, Y, Z]`` of the past frames and the present (last), each in its
            own ego frame.
        poses: their planar poses ``[T, 3]`` in the present frame (the last is zero).
    Returns:
        the present's agents (:func:`~t3fast.agents.tracker.frame_agents`) and their :class:`AgentBoxes`.
    """
    if frames.dim() != 4 or poses.shape != (frames.shape[0], 3):
        raise ValueError(f"fit_agent_boxes: frames must be [T, X, Y, Z] and poses [T, 3], got "
                         f"{list(frames.shape)} and {list(poses.shape)}")
    poses = poses.to(frames.device, torch.float64)
    wanted = frames.new_tensor(AGENT_CLASSES)
    agents = [frame_agents(f, wanted) for f in frames]
    now = agents[-1]
    n = now["cls"].shape[0]
    empty = poses.new_zeros(n)
    if n == 0:
        return now, AgentBoxes(empty.view(0, 2), empty.view(0, 2), empty, empty, empty, empty.long(),
                               empty.long(), now["cls"], empty.bool(), empty.view(0, frames.shape[0], 2))
    match = follow_agents(agents, poses)
    columns = (now["ids"] > 0).nonzero()
    owner = now["ids"][columns[:, 0], columns[:, 1]] - 1
    offset = columns.double() - now["centroid"][owner]
    spread = empty.clone().scatter_reduce_(0, owner, offset.norm(dim=-1), "amax", include_self=True)
    # start: the present centroid, the last step's velocity, the principal axis and extents
    centre = cell_metres(now["centroid"], poses[-1])
    velocity = torch.zeros_like(centre)
    before = match[:, -2] >= 0 if match.shape[1] > 1 else match.new_zeros(n, dtype=torch.bool)
    if bool(before.any()):
        velocity[before] = centre[before] - cell_metres(agents[-2]["centroid"][match[before, -2]], poses[-2])
    spread_m = offset * VOXEL_SIZE
    cov = poses.new_zeros(n, 2, 2).index_add_(0, owner, spread_m[:, :, None] * spread_m[:, None, :])
    axis = torch.linalg.eigh(cov + 1e-9 * torch.eye(2, dtype=torch.float64, device=cov.device))[1][..., 1]
    along = (spread_m * axis[owner]).sum(-1).abs()
    across = (spread_m[:, 1] * axis[owner, 0] - spread_m[:, 0] * axis[owner, 1]).abs()
    length = empty.clone().scatter_reduce_(0, owner, along, "amax", include_self=True) * 2 + VOXEL_SIZE
    width = empty.clone().scatter_reduce_(0, owner, across, "amax", include_self=True) * 2 + VOXEL_SIZE
    params = torch.cat([centre, velocity, torch.atan2(axis[:, 1], axis[:, 0])[:, None], length.log()[:, None],
                        width.log()[:, None]], 1)
    fitted = spread + 3 <= MAX_REACH  # larger: merged agents (a queue, a truck and its trailer)
    iou = empty.clone()
    if bool(fitted.any()):
        group = fitted.nonzero().squeeze(1)
        params[group], iou[group] = _optimise(params[group], _samples(agents, match[group], poses, spread[group] + 3),
                                              iters)
    centre, velocity, yaw = params[:, :2], params[:, 2:4], params[:, 4]
    length, width = params[:, 5].exp(), params[:, 6].exp()
    votes = match.new_zeros(n, NUM_CLASSES).index_put_(
        (now["component"], now["label"]), torch.ones_like(now["label"]), accumulate=True)
    z = now["ijz"][:, 2]
    bottom = match.new_full((n,), frames.shape[-1]).scatter_reduce_(0, now["component"], z, "amin")
    top = match.new_zeros(n).scatter_reduce_(0, now["component"], z + 1, "amax")
    drawn = (iou >= MIN_FIT_IOU) & (votes.max(1).values == votes.sum(1)) & ((match >= 0).sum(1) >= 2)
    return now, AgentBoxes(centre, velocity, yaw, length, width, bottom, top, now["cls"], drawn,
                           _tracks(agents, match, poses))


def _tracks(agents: list[dict[str, Tensor]], match: Tensor, poses: Tensor) -> Tensor:
    """Each followed agent's column centroid in every frame (:func:`follow_agents`' ``match``
    ``[n, T]``), in the present frame: ``[n, T, 2]`` metres, NaN where it was not found."""
    tracks = []
    for t, frame in enumerate(agents):
        centroid = torch.cat([frame["centroid"], frame["centroid"].new_full((1, 2), math.nan)])  # last: not found
        index = torch.where(match[:, t] >= 0, match[:, t], centroid.shape[0] - 1)
        tracks.append(cell_metres(centroid[index], poses[t]))
    return torch.stack(tracks, 1)


def draw_agent_boxes(volume: Tensor, centre: Tensor, yaw: Tensor, length: Tensor, width: Tensor, bottom: Tensor,
                     top: Tensor, label: Tensor, pose: Tensor) -> None:
    """Draw boxes into a label volume ``[X, Y, Z]`` (uint8) in place: box ``i`` (centre ``[m, 2]``,
    yaw, length, width ``[m]`` in the present frame, metres) fills the levels ``bottom[i]`` to
    ``top[i]`` (exclusive) of every column whose centre lies inside its footprint, and the
    column under its centre, with ``label[i]``; where boxes overlap, the later one's. ``pose``
    ``[3]``: the volume's ego pose in the present frame (the boxes are taken into it). The
    footprint test is :func:`~t3fast.data.classes.box_footprint`'s, for all boxes at once on
    the volume's device (:func:`t3fast.ops.draw_boxes`), within ``DRAW_REACH`` columns of each
    box's centre column."""
    device = volume.device
    pose = pose.to(device, torch.float64)
    c, s = torch.cos(pose[2]), torch.sin(pose[2])
    d = centre.to(device, torch.float64) - pose[:2]
    heading = yaw.to(device, torch.float64) - pose[2]
    boxes = torch.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], torch.cos(heading), torch.sin(heading),
                         length.to(device, torch.float64) / 2, width.to(device, torch.float64) / 2], -1)
    levels = torch.stack([bottom, top], -1).to(device, torch.long)
    drawn = ops.draw_boxes(volume[None], boxes[None], levels, label.to(device, torch.uint8), GRID_LOWER[:2],
                           VOXEL_SIZE, DRAW_REACH)
    volume.copy_(drawn[0])
