"""RoutePlanner: the ego's next displacements as a correction to constant speed and turn rate,
read from the road ahead, the ego's past motion and the route command.

Much of the ego's future is visible in the present scene (it brakes behind traffic, slows for
curves, turns where the road turns); which way it goes at the next junction is what a route
command says (:mod:`t3fast.data.route`). The planner reads, in a window ahead of the ego
(:data:`AHEAD`: 8 m behind to 40 m ahead, 24 m to each side; 3 s at 13 m/s), the present
ego-aligned xy plane and its change since the previous frame (what moves there), with a small
strided CNN; an MLP adds the past displacements and the command (one-hot; all zero when no
command is given: trained with the command dropped from a share of windows, it plans without
one too) and predicts each future step's displacement minus constant turn rate's. Its last
layer starts at zero: the untrained planner is constant turn rate exactly.

Compared with the papers' Phi_act (:class:`~t3fast.models.planner.MotionPlanner`, kept as the
``planner="phi_act"`` row), it reads the present scene rather than the forecast triplanes, and
plans all steps in one pass.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from t3fast.data.classes import GRID_LOWER, GRID_UPPER
from t3fast.data.route import COMMANDS
from t3fast.models.blocks import group_norm
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.planner import constant_turn_rate

AHEAD = ((-8.0, 40.0), (-24.0, 24.0))  # metres along x and y (present frame) the planner reads
ROUTE_WIDTHS = (16, 32, 32, 32)  # the CNN's stride-2 stages
ROUTE_HIDDEN = 128


def ahead_window(plane_shape: tuple[int, int]) -> tuple[slice, slice]:
    """The xy-plane cells of :data:`AHEAD` for a plane of ``(H, W)`` cells over the grid."""
    cells = []
    for axis, (lo, hi) in enumerate(AHEAD):
        size = (GRID_UPPER[axis] - GRID_LOWER[axis]) / plane_shape[axis]
        first = max(0, round((lo - GRID_LOWER[axis]) / size))
        last = min(plane_shape[axis], round((hi - GRID_LOWER[axis]) / size))
        cells.append(slice(first, last))
    return cells[0], cells[1]


class RoutePlanner(nn.Module):
    """Args:
        channels: xy-plane channels C.
        plane_shape: the xy plane's ``(H, W)``.
        steps: future steps planned.
        past: past displacements read.
        scene: read the road ahead; False: the past displacements and the command only (the
            planes are accepted and not read).
        modes: candidate plans, each with a score; the plan is the best-scored one (trained
            winner-takes-all: a mode can be nearly exact where one plan would hedge between
            futures). One mode: the plain correction.
    """

    reads_command = True

    def __init__(self, channels: int, plane_shape: tuple[int, int], steps: int = 6, past: int = 4,
                 scene: bool = True, modes: int = 1):
        super().__init__()
        self.steps, self.past, self.modes = steps, past, modes
        self.window = ahead_window(plane_shape)
        self.scene: nn.Module | None = None
        if scene:
            layers: list[nn.Module] = []
            cin = 2 * channels
            for width in ROUTE_WIDTHS:
                layers += [nn.Conv2d(cin, width, 3, stride=2, padding=1), group_norm(width), nn.SiLU()]
                cin = width
            self.scene = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(4), nn.Flatten(),
                                       nn.Linear(16 * cin, ROUTE_HIDDEN), nn.SiLU())
        self.head = nn.Sequential(
            nn.Linear((ROUTE_HIDDEN if scene else 0) + 2 * past + len(COMMANDS), ROUTE_HIDDEN), nn.SiLU(),
            nn.Linear(ROUTE_HIDDEN, ROUTE_HIDDEN), nn.SiLU(),
            nn.Linear(ROUTE_HIDDEN, (2 * steps + 1) * modes if modes > 1 else 2 * steps),
        )
        nn.init.zeros_(self.head[-1].bias)  # untrained: constant turn rate
        if modes > 1:  # the modes must differ to be told apart (winner-takes-all)
            nn.init.normal_(self.head[-1].weight, std=1e-3)
        else:
            nn.init.zeros_(self.head[-1].weight)

    @classmethod
    def from_config(cls, autoencoder: AutoencoderConfig, world: WorldModelConfig) -> RoutePlanner:
        """The (untrained) route planner of a world model of these sizes."""
        return cls(autoencoder.channels, autoencoder.plane_shape[:2], steps=world.steps, past=world.past_actions,
                   scene=world.route_scene, modes=world.route_modes)

    def forward(self, present: Tensor, previous: Tensor, past_actions: Tensor, command: Tensor | None = None) -> Tensor:
        """``present``, ``previous``: xy planes ``[B, C, H, W]`` of the present and the frame
        before (ego-aligned); ``past_actions`` ``[B, T, 2]`` (present frame, metres per step;
        the last ``past`` are read); ``command`` int64 ``[B]`` (:mod:`t3fast.data.route`; -1: none
        for that window) or None (none for any) -> displacements ``[B, steps, 2]`` (the
        best-scored mode)."""
        plans, scores = self.candidates(present, previous, past_actions, command)
        best = scores.argmax(dim=1)
        return plans[torch.arange(plans.shape[0], device=plans.device), best]

    def candidates(self, present: Tensor, previous: Tensor, past_actions: Tensor,
                   command: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Every mode's displacements ``[B, modes, steps, 2]`` and scores ``[B, modes]`` (logits;
        zero for one mode); arguments as :meth:`forward`."""
        b = present.shape[0]
        if past_actions.shape[1] < self.past:
            raise ValueError(f"RoutePlanner reads {self.past} past displacements, got {past_actions.shape[1]}")
        onehot = present.new_zeros(b, len(COMMANDS))
        if command is not None:
            given = (command >= 0).unsqueeze(1)
            # compared, not F.one_hot, which reads the ids' range on the host (the forecast checks them)
            kinds = torch.arange(len(COMMANDS), device=command.device)
            onehot = (command.long()[:, None] == kinds).to(present.dtype) * given
        recent = past_actions[:, -self.past :]
        # metres per step / 5: the inputs stay near unit scale up to 10 m/s
        features = [recent.flatten(1).to(present.dtype) / 5.0, onehot]
        if self.scene is not None:
            rows, cols = self.window
            features.insert(0, self.scene(torch.cat([present, present - previous], dim=1)[:, :, rows, cols]))
        out = self.head(torch.cat(features, dim=1))
        correction = out[:, : 2 * self.steps * self.modes].view(b, self.modes, self.steps, 2)
        scores = out[:, 2 * self.steps * self.modes :] if self.modes > 1 else out.new_zeros(b, 1)
        return constant_turn_rate(recent, self.steps).to(correction.dtype).unsqueeze(1) + correction, scores
