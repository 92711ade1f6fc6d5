"""The stage-2 training forwards: the world model as DDP sees it, one forward per kind of
forecaster (one call, so DDP sees one graph). Each is a :class:`T3Former` (same weights, same
checkpoints) whose ``forward`` is the rollout its loss reads."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.models.route_planner import RoutePlanner
from t3fast.models.triplane import Triplane
from t3fast.models.world_model import T3Former


class RolloutModel(T3Former):
    """The Delta forecaster's (and the papers') training: an autoregressive rollout from any
    future step, its plan, and the decoder's logits at query points."""

    def rollout(self, past: Triplane, past_actions: Tensor, steps: int,
                first_step: int = 0) -> tuple[list[Triplane], Tensor]:
        """Future triplanes and displacements ``[B, steps, 2]`` (differentiable).

        Args:
            past: planes ``[B, T, C, H, W]`` of the frames before future step ``first_step``.
            past_actions: ``[B, T_p + first_step, 2]`` displacements so far (present frame).
        """
        futures, deltas = self.forecaster(past, steps, first_step)
        if isinstance(self.planner, RoutePlanner):
            if first_step != 0:
                raise ValueError(f"the route planner plans every step from the present, not from step {first_step}")
            return futures, self.planner(past.xy[:, -1], past.xy[:, -2], past_actions, None)[:, :steps]
        # The planning loss does not reach the forecaster: its gradient through the predicted
        # triplanes competes with the triplane loss and stalls forecasting (see the tests).
        plan_in = [[t.map(torch.Tensor.detach) for t in ts] for ts in (futures, deltas)]
        present = past.map(lambda p: p[:, -1])
        return futures, self.planner(present, plan_in[0], plan_in[1], past_actions, first_step)

    def forward(self, past: Triplane, past_actions: Tensor, steps: int, first_step: int = 0,
                points: list[Tensor] | None = None) -> tuple[list[Triplane], Tensor, list[Tensor] | None]:
        """(:meth:`rollout`'s futures and displacements, decoder logits ``[B, N, K]`` of each future
        triplane at ``points[k]`` ``[B, N, 3]``, or None without points)."""
        futures, actions = self.rollout(past, past_actions, steps, first_step)
        logits = None if points is None else [self.decoder(t, p) for t, p in zip(futures, points)]
        return futures, actions, logits


class FlowMotionModel(T3Former):
    """The flow forecaster's training: all future steps at once from the present history, and
    the route planner's plans of its own windows when it trains in the same step."""

    def forward(self, past: Triplane, velocity: Tensor | None,
                plan_from: tuple[Tensor, Tensor, Tensor, Tensor] | None = None
                ) -> tuple[list[Triplane], Tensor, Tensor, Tensor | None]:
        """(the future triplanes, forward displacements of the present cells ``[B, S, 2, H, W]``,
        Deltas ``[B, S, C, H, W]``:
        :meth:`~t3fast.models.flow_forecaster.FlowTriplaneForecaster.predict` of ``past`` and the
        tracker's ``velocity``) and the route planner's displacements ``[B, S, 2]`` for
        ``plan_from`` (present and previous xy planes, past displacements, commands; other windows
        than the forecaster's may be), else None."""
        if plan_from is not None and not self.reads_command:
            raise ValueError("plan_from is the route planner's input: it needs world_config.planner = 'route'")
        actions = None if plan_from is None else self.planner(*plan_from)
        return (*self.forecaster.predict(past, velocity), actions)
