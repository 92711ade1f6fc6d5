"""Pure-PyTorch references of the fused operators: same signatures, same results.

They are the ground truth the C++/CUDA kernels are tested against, and the fallback for
devices without a compiled kernel. They materialise every intermediate tensor, which is
exactly what the fused kernels avoid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


def grid_coordinates(
    grid: Sequence[int],
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Voxel-centre coordinates of an ``X x Y x Z`` grid, ``q = (2 i + 1) / N - 1``.

    Returns:
        ``[X, Y, Z, 3]`` tensor of (x, y, z) in (-1, 1).
    """
    axes = [(2 * torch.arange(n, device=device, dtype=dtype) + 1) / n - 1 for n in grid]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)


def positional_encoding(coords: Tensor, pe_freqs: int) -> Tensor:
    """Sin/cos encoding of coordinates.

    Args:
        coords: ``[..., 3]`` (x, y, z).
        pe_freqs: number of frequencies F.

    Returns:
        ``[..., 6 F]`` ordered ``[sin(2^0 x), sin(2^0 y), sin(2^0 z), cos(2^0 x), cos(2^0 y),
        cos(2^0 z), sin(2^1 x), ...]``.
    """
    parts = []
    for k in range(pe_freqs):
        scaled = coords * (2.0**k)
        parts += [torch.sin(scaled), torch.cos(scaled)]
    if not parts:
        return coords.new_zeros(*coords.shape[:-1], 0)
    return torch.cat(parts, dim=-1)


def _sample(plane: Tensor, rows: Tensor, cols: Tensor) -> Tensor:
    """Bilinear, border-clamped lookup of ``plane [B, C, H, W]`` at ``rows``/``cols`` [B, N].

    Returns ``[B, N, C]``. ``rows`` index dim -2, ``cols`` dim -1 (grid_sample's y and x).
    """
    grid = torch.stack([cols, rows], dim=-1).unsqueeze(1)  # [B, 1, N, 2]
    out = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[:, :, 0].transpose(1, 2)


def triplane_features(xy: Tensor, xz: Tensor, yz: Tensor, points: Tensor, pe_freqs: int) -> Tensor:
    """Decoder input features of query points: ``[xy + xz + yz sample, PE]``.

    Args:
        xy, xz, yz: ``[B, C, X', Y']``, ``[B, C, X', Z']``, ``[B, C, Y', Z']``.
        points: ``[B, N, 3]`` (x, y, z) in [-1, 1].

    Returns:
        ``[B, N, C + 6 * pe_freqs]``.
    """
    x, y, z = points.unbind(-1)
    summed = _sample(xy, x, y) + _sample(xz, x, z) + _sample(yz, y, z)
    return torch.cat([summed, positional_encoding(points, pe_freqs)], dim=-1)


def mlp(features: Tensor, weights: Sequence[Tensor], biases: Sequence[Tensor]) -> Tensor:
    """Linear layers with ReLU between them (none after the last)."""
    h = features
    for i, (w, b) in enumerate(zip(weights, biases)):
        h = F.linear(h, w, b)
        if i + 1 < len(weights):
            h = torch.relu(h)
    return h


def triplane_decode(
    xy: Tensor,
    xz: Tensor,
    yz: Tensor,
    weights: Sequence[Tensor],
    biases: Sequence[Tensor],
    *,
    grid: Sequence[int] | None = None,
    points: Tensor | None = None,
    pe_freqs: int = 6,
    argmax: bool = False,
    live: Tensor | None = None,
) -> Tensor:
    """Reference of :func:`t3fast.ops.triplane_decode` (see there for the contract)."""
    if (grid is None) == (points is None):
        raise ValueError("t3fast.triplane_decode: exactly one of grid and points must be given")
    batch = xy.shape[0]
    if grid is not None:
        coords = grid_coordinates(grid, device=xy.device, dtype=xy.dtype)
        query = coords.reshape(1, -1, 3).expand(batch, -1, -1)
        out_shape = (batch, *grid)
    else:
        query = points
        out_shape = tuple(points.shape[:2])
    logits = mlp(triplane_features(xy, xz, yz, query, pe_freqs), weights, biases)
    if argmax:
        labels = logits.argmax(-1).to(torch.uint8).reshape(out_shape)
        if live is not None:  # the points beyond each element's count: label 0
            decoded = torch.arange(labels.shape[1], device=labels.device) < live[:, None]
            labels = torch.where(decoded, labels, torch.zeros_like(labels))
        return labels
    return logits.reshape(*out_shape, logits.shape[-1])


def axis_pool(volume: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Axis means of ``volume [B, C, X, Y, Z]``.

    Returns:
        ``xy [B, C, X, Y]`` (mean over Z), ``xz [B, C, X, Z]`` (over Y),
        ``yz [B, C, Y, Z]`` (over X).
    """
    return volume.mean(dim=4), volume.mean(dim=3), volume.mean(dim=2)


def delta_fuse(delta: Tensor, prev: Tensor, weight: Tensor, bias: Tensor | None = None) -> Tensor:
    """``delta [B, C, H, W] + conv1x1(prev [B, C_in, H, W], weight [C, C_in]) + bias [C]``."""
    out = delta + torch.einsum("oc,bchw->bohw", weight, prev)
    if bias is not None:
        out = out + bias[None, :, None, None]
    return out


def matching_costs(present: Tensor, previous: Tensor, radius: int) -> Tensor:
    """:func:`t3fast.ops.matching_costs` one row of shifts at a time: ``[B, C, H, 2r + 1, W]``
    differences in memory per row."""
    b, c, h, w = present.shape
    padded = F.pad(previous, (radius,) * 4, mode="replicate")
    size = 2 * radius + 1
    rows = []
    for di in range(size):
        shifted = padded[..., di : di + h, :].unfold(-1, w, 1)  # [B, C, H, size (d_j), W]
        rows.append((present.unsqueeze(3) - shifted).abs_().sum(1))  # [B, H, size, W]
    # the channel mean's division and sign applied once, to the 1/C-sized result
    return torch.stack(rows, 1).permute(0, 1, 3, 2, 4).reshape(b, size * size, h, w).div_(-c)


def group_norm_silu(input: Tensor, weight: Tensor, bias: Tensor, groups: int, eps: float = 1e-5,
                    residual: Tensor | None = None) -> Tensor:
    """``silu(group_norm(input) * weight + bias [+ residual])`` as the three ops it fuses."""
    out = F.group_norm(input, groups, weight, bias, eps)
    return F.silu(out if residual is None else out + residual)


def label_conv3d(labels: Tensor, table: Tensor) -> Tensor:
    """``out[b, :, v] = sum over the 27 taps t of table[t, labels[b, v + t], :]`` (nothing from
    outside the volume): ``labels [B, X, Y, Z]`` (class ids in ``[0, K)``), ``table [27, K, C]``
    -> ``[B, C, X, Y, Z]``; as a convolution of the one-hot labels."""
    classes, channels = table.shape[1:]
    one_hot = F.one_hot(labels.long(), classes).permute(0, 4, 1, 2, 3).to(table.dtype)
    weight = table.reshape(3, 3, 3, classes, channels).permute(4, 3, 0, 1, 2)
    return F.conv3d(one_hot, weight, padding=1)


def bev_components(mask: Tensor) -> tuple[Tensor, Tensor]:
    """8-connected components of BEV masks ``[B, X, Y]`` (bool) by label propagation: every
    cell takes the largest label of its 3x3 neighbourhood and then the label its label points
    at (pointer jumping, so a component of diameter d converges in about log d rounds rather
    than d), until nothing changes; each component ends labelled by its last cell.

    Returns:
        labels int64 ``[B, X, Y]`` (0 off the mask, 1..n on it in the row-major order of each
        component's last cell) and n int64 ``[B]``.
    """
    b, nx, ny = mask.shape
    if mask.numel() == 0:
        return torch.zeros(b, nx, ny, dtype=torch.long, device=mask.device), torch.zeros(
            b, dtype=torch.long, device=mask.device)
    keep = mask.float()
    # labels are 1 + the flat index of a cell of the same component (exact in float32 below 2^24)
    labels = torch.arange(1, nx * ny + 1, dtype=torch.float32, device=mask.device).view(1, nx, ny) * keep
    while True:
        pooled = F.max_pool2d(labels[:, None], 3, stride=1, padding=1)[:, 0] * keep
        flat = pooled.flatten(1)
        jumped = torch.maximum(flat, flat.gather(1, (flat.long() - 1).clamp(min=0)) * keep.flatten(1))
        jumped = jumped.view(b, nx, ny)
        if torch.equal(jumped, labels):
            break
        labels = jumped
    last = labels.long().flatten(1)  # 1 + each component's last cell
    index = torch.arange(1, nx * ny + 1, device=mask.device)
    rank = (last == index).cumsum(1)  # a component's number: how many components end up to its last cell
    out = torch.where(last > 0, rank.gather(1, (last - 1).clamp(min=0)), 0)
    return out.view(b, nx, ny), rank[:, -1]


def draw_boxes(volume: Tensor, boxes: Tensor, levels: Tensor, labels: Tensor, lower: Sequence[float],
               voxel_size: float, reach: int) -> Tensor:
    """Boxes drawn into label volumes, all at once: every box's window of ``(2 reach + 1)^2``
    columns around its centre column, each covered voxel marked with the box's number, the
    largest number of each voxel (the last box) giving its label.

    Args:
        volume: uint8 ``[B, X, Y, Z]``.
        boxes: float64 ``[B, M, 6]``: centre x, y, the cosine and sine of the heading, half the
            length, half the width (metres, in the volume's frame).
        levels: int64 ``[M, 2]``: the levels ``bottom <= z < top`` each box fills; or
            ``[B, M, 2]``, each volume's.
        labels: uint8 ``[M]``, or ``[B, M]`` with ``[B, M, 2]`` levels.
        lower: the grid's lower x and y (metres); voxel_size: metres per column.
        reach: columns from the centre column tested along each axis.

    Returns:
        the drawn volumes, uint8 ``[B, X, Y, Z]``.
    """
    b, nx, ny, nz = volume.shape
    m, device = boxes.shape[1], volume.device
    if m == 0 or volume.numel() == 0:
        return volume.clone()
    x, y, c, s, half_length, half_width = (boxes[..., i] for i in range(6))  # [B, M]
    offsets = torch.arange(-reach, reach + 1, device=device)
    rows = torch.floor((x - lower[0]) / voxel_size).long()[..., None] + offsets  # [B, M, W]
    cols = torch.floor((y - lower[1]) / voxel_size).long()[..., None] + offsets
    dx = (lower[0] + voxel_size * (rows.double() + 0.5) - x[..., None])[..., :, None]  # [B, M, W, 1]
    dy = (lower[1] + voxel_size * (cols.double() + 0.5) - y[..., None])[..., None, :]  # [B, M, 1, W]
    c, s = c[..., None, None], s[..., None, None]
    inside = ((c * dx + s * dy).abs() <= half_length[..., None, None]) & (
        (-s * dx + c * dy).abs() <= half_width[..., None, None])
    inside[..., reach, reach] = True  # the column under the centre: small agents never vanish
    inside &= ((rows >= 0) & (rows < nx))[..., :, None] & ((cols >= 0) & (cols < ny))[..., None, :]
    z = torch.arange(nz, device=device)
    spans = (z >= levels[..., :1]) & (z < levels[..., 1:])  # [M, Z], or [B, M, Z] per volume
    cover = inside[..., None] & spans[..., :, None, None, :]  # [B, M, W, W, Z]
    column = rows.clamp(0, nx - 1)[..., :, None] * ny + cols.clamp(0, ny - 1)[..., None, :]  # [B, M, W, W]
    batch = torch.arange(b, device=device).view(b, 1, 1, 1, 1) * (nx * ny * nz)
    voxel = batch + column[..., None] * nz + z
    number = torch.arange(1, m + 1, device=device).view(1, m, 1, 1, 1) * cover  # 0 where a box does not draw
    winner = torch.zeros(b * nx * ny * nz, dtype=torch.long, device=device).scatter_reduce_(
        0, voxel.flatten(), number.flatten(), "amax").view(volume.shape)
    if labels.dim() == 2:  # each volume's: the volume's row of labels
        labels = labels.flatten()
        winner = torch.where(winner > 0, winner + torch.arange(b, device=device).view(b, 1, 1, 1) * m, 0)
    return torch.where(winner > 0, labels[(winner - 1).clamp(min=0)], volume)


# ---------------------------------------------------------------- box_fit
@dataclass
class FitSamples:
    """One window's box-fit samples, flat over its agents and frames, float32 around each
    agent's starting centre: ``points`` ``[N, 2]`` (metres), ``time`` ``[N]`` (steps before the
    present, <= 0), ``agent`` ``[N]`` int64, ``owned`` ``[N]`` (1: one of the agent's columns),
    ``count`` the loss's normaliser (the number of samples, at least 1)."""

    points: Tensor
    time: Tensor
    agent: Tensor
    owned: Tensor
    count: int


def _fit_margins(params: Tensor, samples: FitSamples) -> tuple[Tensor, ...]:
    """(the footprint margin ``[N]`` of every sample under the boxes ``params`` ``[n, 9]``, and
    the terms its gradient reads)."""
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


def fit_loss(params: Tensor, samples: FitSamples, softness: float, accel_prior: float) -> Tensor:
    """The objective :func:`box_fit` descends: the summed logistic loss of the soft
    inside/outside (signed footprint distance over ``softness`` metres) against each sample's
    ownership, over the samples' count, plus the zero-acceleration prior ``accel_prior`` per
    agent. ``params`` ``[n, 9]``: centre, velocity per step, yaw, log length, log width,
    acceleration per step^2 (differentiable: the fit uses :func:`fit_gradient`)."""
    margin = _fit_margins(params, samples)[0]
    loss = F.binary_cross_entropy_with_logits(margin / softness, samples.owned, reduction="sum")
    return loss / samples.count + accel_prior * params[:, 7:9].pow(2).sum() / params.shape[0]


def fit_gradient(params: Tensor, samples: FitSamples, softness: float, accel_prior: float) -> Tensor:
    """The gradient ``[n, 9]`` of :func:`fit_loss` with respect to ``params``, in closed form.
    Where the footprint's two distances tie, each takes half, as ``torch.minimum``'s gradient
    does."""
    margin, by_length, by_width, along, across, c, s, half_length, half_width = _fit_margins(params, samples)
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
    grad[:, 7:9] += 2 * accel_prior / params.shape[0] * params[:, 7:9]
    return grad


def box_fit_samples(ids: Tensor, track: Tensor, centroid: Tensor, poses: Tensor, reach: Tensor,
                    lower: Sequence[float], voxel_size: float, near: int) -> dict[str, Tensor]:
    """The columns that decide each agent's box in one window (:func:`box_fit`'s arguments of
    one batch element, the agents to fit only): in every frame ``t`` where the agent was found,
    the grid columns within ``reach`` (Euclidean, in cells) of its rounded centroid and within
    ``near`` columns (along each axis) of one it owns. Flat over frames, then agents, then the
    window's rows and columns: ``position`` ``[N, 2]`` (float64 metres in the present frame),
    ``owned`` ``[N]``, ``agent`` ``[N]`` and ``time`` ``[N]`` (``t - (T - 1)``)."""
    frames, nx, ny = ids.shape
    n = track.shape[0]
    half = int(reach.max().ceil()) + near if n else near
    side = torch.arange(-half, half + 1, device=ids.device)
    offsets = torch.stack(torch.meshgrid(side, side, indexing="ij"), -1).reshape(-1, 2)
    within = offsets.double().norm(dim=-1)[None] <= reach[:, None]  # [n, P]
    width = 2 * half + 1
    out: dict[str, list[Tensor]] = {"position": [], "owned": [], "agent": [], "time": []}
    for t in range(frames):
        index = track[:, t]
        seen = index >= 0
        cells = torch.where(seen[:, None], centroid[:, t], 0.0).round().long()[:, None] + offsets
        inside = (cells[..., 0] >= 0) & (cells[..., 0] < nx) & (cells[..., 1] >= 0) & (cells[..., 1] < ny)
        cells = torch.stack([cells[..., 0].clamp(0, nx - 1), cells[..., 1].clamp(0, ny - 1)], -1)
        owned = (ids[t][cells[..., 0], cells[..., 1]] == index[:, None] + 1) & inside
        close = F.max_pool2d(owned.view(n, 1, width, width).float(), 2 * near + 1, 1, near).view(n, -1) > 0
        keep = (inside & within & close & seen[:, None]).nonzero()
        cell = cells[keep[:, 0], keep[:, 1]].double()
        local = torch.tensor(lower, dtype=torch.float64, device=ids.device) + (cell + 0.5) * voxel_size
        pose = poses[t]
        c, s = torch.cos(pose[2]), torch.sin(pose[2])
        out["position"].append(torch.stack([pose[0] + c * local[:, 0] - s * local[:, 1],
                                            pose[1] + s * local[:, 0] + c * local[:, 1]], -1))
        out["owned"].append(owned[keep[:, 0], keep[:, 1]].double())
        out["agent"].append(keep[:, 0])
        out["time"].append(poses.new_full((keep.shape[0],), float(t - (frames - 1))))
    return {k: torch.cat(v) for k, v in out.items()}


def fit_adam(start: Tensor, found: dict[str, Tensor], iters: int, lr: float, softness: Sequence[float],
             accel_prior: float) -> tuple[Tensor, Tensor]:
    """Boxes ``[n, 7]`` fitted from ``start`` to the samples ``found`` (:func:`box_fit_samples`)
    and each one's footprint IoU with its columns over the frames ``[n]``: ``iters`` Adam steps
    (learning rate ``lr``, the default betas) on :func:`fit_gradient`, the softness narrowing
    geometrically from ``softness[0]`` to ``softness[1]``, in float32 around each agent's
    starting centre."""
    agent = found["agent"]
    samples = FitSamples((found["position"] - start[agent, :2]).float(), found["time"].float(), agent,
                         found["owned"].float(), max(agent.numel(), 1))
    offset = start.clone()
    offset[:, 2:] = 0
    n = start.shape[0]
    params = torch.cat([(start - offset).float(), start.new_zeros(n, 2, dtype=torch.float32)], 1)
    mean, square = torch.zeros_like(params), torch.zeros_like(params)
    beta1, beta2 = 0.9, 0.999
    for it in range(iters):
        soft = softness[0] * (softness[1] / softness[0]) ** (it / max(iters - 1, 1))
        grad = fit_gradient(params, samples, soft, accel_prior)
        mean.lerp_(grad, 1 - beta1)
        square.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
        denom = (square.sqrt() / math.sqrt(1 - beta2 ** (it + 1))).add_(1e-8)
        params.addcdiv_(mean, denom, value=-lr / (1 - beta1 ** (it + 1)))
    inside = (_fit_margins(params, samples)[0] > 0).float()
    owned = samples.owned
    both = owned.new_zeros(n).index_add_(0, agent, inside * owned)
    either = owned.new_zeros(n).index_add_(0, agent, (inside + owned).clamp(max=1))
    return params[:, :7].double() + offset, (both / either.clamp(min=1)).double()


def box_fit(ids: Tensor, track: Tensor, centroid: Tensor, poses: Tensor, start: Tensor, reach: Tensor,
            lower: Sequence[float], voxel_size: float, window: int, near: int, iters: int, lr: float,
            softness: Sequence[float], accel_prior: float) -> tuple[Tensor, Tensor]:
    """Agents' boxes fitted to their columns in every frame of a window: per batch element, the
    agents with ``reach > 0`` are fitted together (:func:`box_fit_samples`, :func:`fit_adam`;
    the loss normalised by their samples' count and the prior by their number), the others keep
    their start and an IoU of 0. ``reach`` is capped at ``window``.

    Args:
        ids: int64 ``[B, T, X, Y]``: each frame's component map (0 off the agents, else 1 + component).
        track: int64 ``[B, n, T]``: each agent's component in every frame, -1 where not found.
        centroid: float64 ``[B, n, T, 2]``: that component's column centroid (cells; read where found).
        poses: float64 ``[B, T, 3]``: each frame's planar pose in the present frame.
        start: float64 ``[B, n, 7]``: centre (metres), velocity per step, yaw, log length, log width.
        reach: float64 ``[B, n]``: cells around the centroid the fit samples; <= 0: not fitted.

    Returns:
        the fitted boxes float64 ``[B, n, 7]`` (the velocity the present one of a constant
        acceleration fitted with them) and the footprint IoU float64 ``[B, n]``.
    """
    params, iou = start.clone(), start.new_zeros(start.shape[:2])
    for b in range(start.shape[0]):
        fitted = (reach[b] > 0).nonzero().squeeze(1)
        if fitted.numel() == 0:
            continue
        found = box_fit_samples(ids[b], track[b, fitted], centroid[b, fitted], poses[b],
                                reach[b, fitted].clamp(max=window), lower, voxel_size, near)
        params[b, fitted], iou[b, fitted] = fit_adam(start[b, fitted], found, iters, lr, softness, accel_prior)
    return params, iou
