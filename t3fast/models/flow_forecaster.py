"""FlowTriplaneForecaster: future triplanes as the present one with its agents moved, plus Delta.

In the ego-aligned frame the static world stands still, so what a forecaster has to produce
is motion: agents carried along their paths, a few cells per step. The papers' Delta
forecaster (:mod:`t3fast.models.forecaster`) has to rebuild a moved car cell by cell from
attention; trained on a 2-core budget it learnt nothing that beat its initialisation. Here
motion is represented as motion, the way a tracker does it:

* the motion starts from the classical tracker: its agent velocities (measured in the last
  three observed frames; ``v`` the mean of the last step's and the chained two-step velocity,
  which moved agents better than the last step alone) give step ``k`` the displacement
  ``(k + 1) v`` at each *present* cell of a tracked agent, and a *motion head*
  (:class:`~t3fast.models.motion_head.ContextMotionHead`, which reads the velocities and the
  scene around each agent) predicts a correction there, so the static world stays exactly
  still. Untrained (its last layer is zero) the forecaster is this tracker in the latent:
  training has to improve on it, not rediscover it. A displacement head of the UNet instead,
  or a per-cell correction from it, fitted the training windows and lowered validation;
* one UNet reads the history of xy planes, their differences, *matching costs* (how well each
  present cell matches each cell around it in the previous frame, and the previous in the one
  before: :func:`~t3fast.ops.matching_costs`) and the velocities, and predicts a
  change Delta for every future step (zero at the start);
* the present plane is moved accordingly: the displacements of the moving cells are splatted
  forward (:func:`~t3fast.models.plane_warp.splat_plane`) into a backward flow at the cells
  they land on, which is one bilinear lookup of the present plane
  (:func:`~t3fast.models.plane_warp.warp_plane`), so a car moves as a whole and stays sharp.
  The cells a moving agent leaves and nothing lands on take a learned fill (what is under a
  car: road), and ``xy_k = delta_fuse(Delta_k, moved_k)`` corrects the rest.

Motion is decided where the car is, not 20 cells ahead at the place it will reach in 3 s (a
backward flow predicted there fitted the training windows but generalised poorly). All six
steps come from one pass (not autoregressive: six times cheaper, and no compounding of a
step's errors through the next step's input).

The xz and yz planes (height profiles pooled along y and x) are carried from the present: the
true future xy plane with the present xz/yz keeps 98 % of what the true future triplane gains
on the moving classes, for a third of the latent.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from t3fast.agents.tracker import VELOCITY_CHANNELS, blended_velocity
from t3fast.models.blocks import group_norm
from t3fast.models.motion_head import ContextMotionHead
from t3fast.models.plane_warp import splat_plane, warp_plane
from t3fast.models.triplane import Triplane
from t3fast.ops import delta_fuse, matching_costs


def _block(cin: int, cout: int, stride: int = 1, convs: int = 2) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(convs):
        layers += [nn.Conv2d(cin if i == 0 else cout, cout, 3, stride=stride if i == 0 else 1, padding=1),
                   group_norm(cout), nn.SiLU()]
    return nn.Sequential(*layers)


class FlowUNet(nn.Module):
    """``[B, C_in, H, W] -> [B, C_out, H, W]``: a UNet with ``len(widths)`` levels (stride 2
    between levels), so the coarsest level sees motions of tens of cells. The full-resolution
    level has one convolution each way (it is most of the cost), the others two."""

    def __init__(self, in_channels: int, out_channels: int, widths: Sequence[int]):
        super().__init__()
        self.down = nn.ModuleList(
            _block(in_channels if v == 0 else widths[v - 1], w, stride=1 if v == 0 else 2, convs=1 if v == 0 else 2)
            for v, w in enumerate(widths)
        )
        self.up = nn.ModuleList(
            _block(widths[v + 1] + widths[v], widths[v], convs=1 if v == 0 else 2) for v in range(len(widths) - 1)
        )
        self.head = nn.Conv2d(widths[0], out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        skips = []
        for down in self.down:
            x = down(x)
            skips.append(x)
        y = skips[-1]
        for v in range(len(skips) - 2, -1, -1):
            y = F.interpolate(y, size=skips[v].shape[-2:], mode="bilinear", align_corners=False)
            y = self.up[v](torch.cat([y, skips[v]], dim=1))
        return self.head(y)


MOVING_CELLS = 0.5  # a displacement of at least this many cells counts as moving content
STILL = 1e-3  # a cell whose moving share and landed content are below this keeps its content as is
MATCH_FEATURES = 32  # channels the matching costs are compressed to before the UNet


def _step_numbers(steps: int, like: Tensor) -> Tensor:
    """``1 .. steps`` shaped ``[1, steps, 1, 1, 1]``: displacement = step number x velocity."""
    return torch.arange(1, steps + 1, device=like.device, dtype=like.dtype).view(1, -1, 1, 1, 1)


def tracker_motion(velocity: Tensor, steps: int) -> Tensor:
    """What the motion head corrects: step ``k``'s displacement ``(k + 1)`` x the tracker's
    blended velocity (:func:`~t3fast.agents.tracker.blended_velocity`) of the velocities
    ``[B, 4, H, W]``, ``[B, steps, 2, H, W]``."""
    return blended_velocity(velocity).unsqueeze(1) * _step_numbers(steps, velocity)


def move_plane(present: Tensor, displacement: Tensor, fill: Tensor) -> Tensor:
    """``present`` ``[B, C, H, W]`` with each cell's content moved by its forward
    ``displacement`` ``[B, 2, H, W]`` (plane cells); cells that moving content leaves and none
    lands on take ``fill`` ``[C]``. Cells moving less than :data:`MOVING_CELLS` count
    proportionally less, so a static world stays put."""
    size = torch.sqrt(displacement.square().sum(1, keepdim=True) + 1e-12)
    moving = (size / MOVING_CELLS).clamp(max=1)  # [B, 1, H, W]
    landed = splat_plane(torch.cat([-displacement * moving, moving], dim=1), displacement)
    cover = landed[:, 2:]
    moved = warp_plane(present, landed[:, :2] / cover.clamp(min=1))
    # the share of a cell that stays put covers it too: only moving content leaves a hole
    vacated = (moving - cover).clamp(min=0)
    out = moved + vacated * (fill.view(1, -1, 1, 1) - moved)
    # where nothing leaves or lands the cell keeps its content exactly (a zero-flow lookup rounds),
    # so a decoder can tell the unchanged cells apart and skip them
    untouched = (moving <= STILL) & (cover <= STILL)
    return torch.where(untouched, present, out)


class FlowTriplaneForecaster(nn.Module):
    """Past planes and the tracker's agent velocities -> the future triplanes of all ``steps``
    steps at once.

    Args:
        channels: triplane channels C.
        plane_shape: ``(X', Y', Z')``.
        widths: channels of the UNet's levels.
        history: past frames read (the present included; at least the 3 the velocities come from).
        steps: future steps predicted.
        flow_scale: plane cells per unit of the velocities the networks read and of the motion
            head's correction, per step.
        match_radius: the matching costs compare each cell with the cells up to this many
            cells away in the previous frame (the fastest agents move ~7 cells a step).
        bev: the latent has only the xy plane.
    """

    def __init__(
        self,
        channels: int = 8,
        plane_shape: tuple[int, int, int] = (100, 100, 16),
        widths: Sequence[int] = (16, 32, 48, 64, 96),
        history: int = 5,
        steps: int = 6,
        flow_scale: float = 2.0,
        match_radius: int = 6,
        bev: bool = False,
    ):
        super().__init__()
        if history < 3:
            raise ValueError(f"FlowTriplaneForecaster reads the 3 history frames the tracker's velocities come "
                             f"from, got {history}")
        self.channels, self.history, self.steps, self.flow_scale, self.bev = channels, history, steps, flow_scale, bev
        self.match_radius, self.match_pairs = match_radius, 2
        costs = self.match_pairs * (2 * match_radius + 1) ** 2
        self.match_stem = nn.Sequential(nn.Conv2d(costs, MATCH_FEATURES, 1), nn.SiLU())  # compress before the 3x3 convs
        inputs = (2 * history - 1) * channels + MATCH_FEATURES + VELOCITY_CHANNELS
        self.unet = FlowUNet(inputs, steps * channels, widths)
        with torch.no_grad():  # Delta starts at zero
            self.unet.head.weight.zero_()
            self.unet.head.bias.zero_()
        self.reset_motion_head()
        # the 1x1 fusion is the identity plus a learned part that starts at 0 (as in the Delta forecaster)
        self.fuse_residual = nn.Parameter(torch.zeros(channels, channels))
        self.fuse_bias = nn.Parameter(torch.zeros(channels))
        self.fill = nn.Parameter(torch.zeros(channels))

    def predict(self, past: Triplane, velocity: Tensor) -> tuple[list[Triplane], Tensor, Tensor]:
        """Past planes ``[B, T, C, H, W]`` (present last, ``T >= history``) and the agents'
        velocities ``[B, 4, H, W]`` (plane cells per step,
        :func:`~t3fast.agents.tracker.tracker_velocities`) -> (the ``steps`` future triplanes,
        forward displacements ``[B, steps, 2, H, W]`` of the present cells in plane cells,
        Deltas ``[B, steps, C, H, W]`` of the xy plane)."""
        xy = past.xy[:, -self.history :]
        b, t, c, h, w = xy.shape
        if t < self.history:
            raise ValueError(f"FlowTriplaneForecaster: {self.history} history frames needed, got {t}")
        if velocity is None or velocity.shape != (b, VELOCITY_CHANNELS, h, w):
            got = None if velocity is None else list(velocity.shape)
            raise ValueError(f"FlowTriplaneForecaster needs the agents' velocities [{b}, {VELOCITY_CHANNELS}, {h}, "
                             f"{w}] (t3fast.forecast.agents.measured_velocities), got {got}")
        velocity = velocity.to(xy.dtype)
        # the pairs (present, previous), (previous, the one before), ... compared in one batch
        pairs = self.match_pairs
        newer, older = xy[:, t - pairs :].flip(1), xy[:, t - 1 - pairs : t - 1].flip(1)
        costs = matching_costs(newer.flatten(0, 1), older.flatten(0, 1), self.match_radius).view(b, -1, h, w)
        inputs = [xy.flatten(1, 2), (xy[:, 1:] - xy[:, :-1]).flatten(1, 2), self.match_stem(costs),
                  velocity / self.flow_scale]
        deltas = self.unet(torch.cat(inputs, dim=1)).view(b, self.steps, c, h, w)
        displacements = self.tracked_motion(velocity, xy[:, -1], xy[:, -2])
        present = xy[:, -1]
        weight = torch.eye(c, dtype=present.dtype, device=present.device) + self.fuse_residual
        # every step at once, the steps folded into the batch
        steps = self.steps
        moved = move_plane(present.unsqueeze(1).expand(b, steps, c, h, w).reshape(b * steps, c, h, w),
                           displacements.reshape(b * steps, 2, h, w), self.fill)
        nxt = delta_fuse(deltas.reshape(b * steps, c, h, w), moved.contiguous(), weight,
                         self.fuse_bias).view(b, steps, c, h, w)
        others = [None if p is None else p[:, -1] for p in past[1:]]
        futures = [Triplane(nxt[:, k], *others) for k in range(steps)]
        return futures, displacements, deltas

    def reset_motion_head(self) -> None:
        """A new motion head: its correction starts at 0, so the forecaster moves the agents
        exactly as the tracker does."""
        self.motion_head = ContextMotionHead(self.channels, self.steps)

    def tracked_motion(self, velocity: Tensor, present: Tensor, previous: Tensor) -> Tensor:
        """The forward displacements ``[B, steps, 2, H, W]`` (plane cells) of the present cells:
        step ``k`` ``(k + 1)`` times the tracker's blended velocity plus the motion head's
        correction on the tracked agents' cells (0 elsewhere), from the velocities
        ``[B, 4, H, W]`` and the present and previous xy planes ``[B, C, H, W]``."""
        b, _, h, w = velocity.shape
        measured = (velocity != 0).any(1, keepdim=True).unsqueeze(1)  # [B, 1, 1, H, W]: cells of tracked agents
        scaled = velocity / self.flow_scale
        correction = self.motion_head(scaled, present, previous, measured[:, 0].to(present.dtype))
        correction = correction.view(b, self.steps, 2, h, w) * measured
        return (blended_velocity(velocity).unsqueeze(1) + correction * self.flow_scale) * _step_numbers(self.steps,
                                                                                                        velocity)

    def forward(self, past: Triplane, velocity: Tensor, steps: int | None = None
                ) -> tuple[list[Triplane], list[Triplane], Tensor]:
        """The first ``steps`` (default all) future triplanes, their changes from the present
        and their forward displacements ``[B, steps, 2, H, W]``; the arguments as for
        :meth:`predict`. All steps come from the observed history at once."""
        steps = self.steps if steps is None else steps
        if not 1 <= steps <= self.steps:
            raise ValueError(f"FlowTriplaneForecaster predicts future steps 0..{self.steps - 1} from the observed "
                             f"history at once; asked for {steps} steps")
        futures, displacements, _ = self.predict(past, velocity)
        futures = futures[:steps]
        present = past.map(lambda p: p[:, -1])
        changes = [Triplane(*(None if f is None else f - p for f, p in zip(fut, present))) for fut in futures]
        return futures, changes, displacements[:, :steps]
