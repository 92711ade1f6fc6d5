"""The motion head: the learned correction of the tracker's agent velocities (flow forecaster).

The tracker's velocity of an agent (its centroid's displacement over the last step) is noisy
(an agent's visible part changes from frame to frame) and says nothing of what the agent will
do next: brake behind a car, slow for a curve, follow its lane round a bend. A motion head
predicts, at each tracked agent's plane cells, a correction of the constant-velocity
displacement for every future step.

:class:`ContextMotionHead` reads the four velocity channels (the last step and the two-step
mean) together with the present xy plane, its change over the last step and where agents are
tracked, through a stack of dilated 3x3 convolutions whose receptive field (63 cells, 50 m)
covers the road ahead of a car and the agents around it, then a per-cell MLP of those
features and the velocities (a per-cell MLP of the velocities alone, which sees nothing of the
scene, moved validation agents worse).

It ends in a zero-initialised layer: untrained, the correction is 0 and the forecaster moves
the agents exactly as the tracker does.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from t3fast.agents.tracker import VELOCITY_CHANNELS

MOTION_HIDDEN = 64  # width of the head's per-cell MLP
CONTEXT_WIDTH = 32  # channels of the context head's dilated convolutions
CONTEXT_DILATIONS = (1, 2, 4, 8, 16)  # receptive field 1 + 2 * sum = 63 plane cells


def _zero_last(head: nn.Sequential) -> nn.Sequential:
    with torch.no_grad():
        head[-1].weight.zero_()
        head[-1].bias.zero_()
    return head


class ContextMotionHead(nn.Module):
    """Velocities and the scene around each agent -> corrections ``[B, 2 steps, H, W]``.

    Args:
        channels: C of the xy plane.
        steps: future steps.
    """

    def __init__(self, channels: int, steps: int):
        super().__init__()
        inputs = VELOCITY_CHANNELS + 1 + 2 * channels
        layers: list[nn.Module] = [nn.Conv2d(inputs, CONTEXT_WIDTH, 1), nn.SiLU()]
        for d in CONTEXT_DILATIONS:
            layers += [nn.Conv2d(CONTEXT_WIDTH, CONTEXT_WIDTH, 3, padding=d, dilation=d), nn.SiLU()]
        self.context = nn.Sequential(*layers)
        self.head = _zero_last(nn.Sequential(
            nn.Conv2d(CONTEXT_WIDTH + VELOCITY_CHANNELS, MOTION_HIDDEN, 1), nn.SiLU(),
            nn.Conv2d(MOTION_HIDDEN, steps * 2, 1),
        ))

    def forward(self, velocity: Tensor, present: Tensor, previous: Tensor, tracked: Tensor) -> Tensor:
        """``velocity`` ``[B, 4, H, W]`` (divided by the flow scale), the present and previous xy
        planes ``[B, C, H, W]``, ``tracked`` ``[B, 1, H, W]`` (1 on tracked agents' cells)."""
        features = self.context(torch.cat([velocity, tracked, present, present - previous], dim=1))
        return self.head(torch.cat([features, velocity], dim=1))
