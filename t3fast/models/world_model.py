"""T3Former: the world model wiring encoder (frozen), forecaster, planner and decoder."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from t3fast.models.config import AutoencoderConfig, WorldModelConfig
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

    @classmethod
    def from_config(cls, autoencoder: AutoencoderConfig, world: WorldModelConfig) -> T3Former:
        """A world model of the given sizes (untrained; load a stage-1 encoder/decoder into it)."""
        bev = autoencoder.latent == "bev"
        forecaster = DeltaTriplaneForecaster(
            channels=autoencoder.channels,
            plane_shape=autoencoder.plane_shape,
            widths=world.forecaster_widths[: world.scales],
            history=world.history,
            steps=world.steps,
            heads=world.forecaster_heads,
            layers=world.forecaster_layers,
            max_tokens=world.max_tokens,
            predict_delta=world.predict_delta,
            bev=bev,
        )
        planner = MotionPlanner(
            channels=autoencoder.channels,
            widths=world.planner_widths,
            d_act=world.d_act,
            steps=world.steps,
            past=world.past_actions,
            heads=world.planner_heads,
            layers=world.planner_layers,
            bev=bev,
        )
        return cls(TriplaneEncoder(autoencoder), forecaster, planner, TriplaneDecoder.from_config(autoencoder))

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
        self, past: Triplane, past_actions: Tensor, steps: int, first_step: int = 0
    ) -> tuple[list[Triplane], list[Triplane], Tensor]:
        """Future triplanes, their changes, and displacements ``[B, steps, 2]`` (differentiable).

        Args:
            past: planes ``[B, T, C, H, W]`` of the frames before future step ``first_step``.
            past_actions: ``[B, T_p + first_step, 2]`` displacements so far (present frame).
        """
        futures, deltas = self.forecaster(past, steps, first_step)
        present = past.map(lambda p: p[:, -1])
        # The planning loss does not reach the forecaster: its gradient through the predicted
        # triplanes competes with the triplane loss and stalls forecasting (see the tests).
        plan_in = [[t.map(torch.Tensor.detach) for t in ts] for ts in (futures, deltas)]
        actions = self.planner(present, plan_in[0], plan_in[1], past_actions, first_step)
        return futures, deltas, actions

    def forward(
        self, past: Triplane, past_actions: Tensor, steps: int, first_step: int = 0, points: list[Tensor] | None = None
    ) -> tuple[list[Triplane], Tensor, list[Tensor] | None]:
        """Training rollout: :meth:`rollout` plus decoder logits ``[B, N, K]`` of each future
        triplane at ``points[k]`` ``[B, N, 3]`` (one forward call, so DDP sees one graph).

        Returns (future triplanes, displacements ``[B, steps, 2]``, logits or None).
        """
        futures, _, actions = self.rollout(past, past_actions, steps, first_step)
        logits = None if points is None else [self.decoder(t, p) for t, p in zip(futures, points)]
        return futures, actions, logits

    @torch.no_grad()
    def forecast(self, past_occupancy: Tensor, past_actions: Tensor, steps: int = 6) -> Forecast:
        """The full forecasting step.

        Args:
            past_occupancy: labels ``[B, T, X, Y, Z]`` of the past frames and the present (last).
            past_actions: ``[B, T - 1, 2]`` past displacements in the present frame.
            steps: future frames (6 = 3 s at 2 Hz).
        """
        return self.forecast_from_triplanes(self.encode_sequence(past_occupancy), past_actions, steps)

    @torch.no_grad()
    def forecast_from_triplanes(self, past: Triplane, past_actions: Tensor, steps: int = 6) -> Forecast:
        """The forecasting step from encoded past frames (planes ``[B, T, C, H, W]``): forecaster,
        planner and decoding to labels. A streaming user encodes each new frame once and keeps
        the planes of the previous ones."""
        futures, _, actions = self.rollout(past, past_actions, steps)
        labels = torch.stack([self.decoder.predict(t) for t in futures], dim=1)
        return Forecast(labels, futures, actions, actions.cumsum(1))
