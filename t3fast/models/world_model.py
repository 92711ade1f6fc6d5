"""T3Former: the world model wiring encoder (frozen), forecaster, planner and decoder."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.forecaster import DeltaTriplaneForecaster
from t3fast.models.planner import MotionPlanner
from t3fast.models.triplane import Triplane


@dataclass
class Forecast:
    """What :meth:`T3Former.forecast` returns for ``S`` future steps.

    Attributes:
        labels: uint8 ``[B, S, X, Y, Z]`` decoded future occupancy (argmax mode).
        triplanes: per step the predicted :class:`Triplane` (planes ``[B, C, H, W]``).
        actions: ``[B, S, 2]`` planned displacements in the present frame.
        trajectory: ``[B, S, 2]`` planned positions, ``actions.cumsum(1)``.
    """

    labels: Tensor
    triplanes: list[Triplane]
    actions: Tensor
    trajectory: Tensor


class T3Former(nn.Module):
    """Past occupancy and motion -> future occupancy, triplanes and ego trajectory.

    The encoder is frozen (stage 2 trains the forecaster and planner and fine-tunes the
    decoder); it stays in eval mode whatever ``train()`` is called with.
    """

    def __init__(
        self,
        encoder: TriplaneEncoder,
        forecaster: DeltaTriplaneForecaster,
        planner: MotionPlanner,
        decoder: TriplaneDecoder,
    ):
        super().__init__()
        self.encoder, self.forecaster, self.planner, self.decoder = encoder, forecaster, planner, decoder
        self.encoder.requires_grad_(False)

    def train(self, mode: bool = True) -> T3Former:
        super().train(mode)
        self.encoder.eval()
        return self

    @torch.no_grad()
    def encode_sequence(self, occupancy: Tensor) -> Triplane:
        """Labels ``[B, T, X, Y, Z]`` -> triplane planes ``[B, T, C, H, W]`` (frozen encoder)."""
        b, t = occupancy.shape[:2]
        planes = self.encoder(occupancy.flatten(0, 1))
        return planes.map(lambda p: p.unflatten(0, (b, t)))

    def rollout(
        self, past: Triplane, past_actions: Tensor, steps: int
    ) -> tuple[list[Triplane], list[Triplane], Tensor]:
        """Future triplanes, their changes, and displacements ``[B, steps, 2]``."""
        futures, deltas = self.forecaster(past, steps)
        present = past.map(lambda p: p[:, -1])
        return futures, deltas, self.planner(present, futures, deltas, past_actions)

    @torch.no_grad()
    def forecast(self, past_occupancy: Tensor, past_actions: Tensor, steps: int = 6) -> Forecast:
        """The full forecasting step.

        Args:
            past_occupancy: labels ``[B, T, X, Y, Z]`` of the past frames and the present (last).
            past_actions: ``[B, T - 1, 2]`` past displacements in the present frame.
            steps: future frames (6 = 3 s at 2 Hz).
        """
        futures, _, actions = self.rollout(self.encode_sequence(past_occupancy), past_actions, steps)
        labels = torch.stack([self.decoder.predict(t) for t in futures], dim=1)
        return Forecast(labels, futures, actions, actions.cumsum(1))
