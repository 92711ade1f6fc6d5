"""T3Former: the world model's networks (encoder, forecaster, planner, decoder, box motion) and
its public forecast, run as the pipeline of stages in :mod:`t3fast.forecast` that its layout
and networks choose once (:func:`~t3fast.forecast.pipeline.build_pipeline`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from torch import Tensor, nn

from t3fast.errors import UsageError
from t3fast.forecast.compiled import compiled_forecast
from t3fast.forecast.encode import encode_sequence
from t3fast.forecast.pipeline import ForecastPipeline, Layout, build_pipeline, check_layout
from t3fast.forecast.records import Forecast
from t3fast.models.box_motion import BoxMotionNet
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.forecast_inputs import (
    check_class_ids,
    check_devices,
    check_past_motion,
    check_past_occupancy,
    check_plan,
    read_together,
)
from t3fast.models.forecaster import DeltaTriplaneForecaster
from t3fast.models.planner import MotionPlanner
from t3fast.models.route_planner import RoutePlanner
from t3fast.models.triplane import Triplane

__all__ = ["Forecast", "Layout", "T3Former"]


class T3Former(nn.Module):
    """Past occupancy and motion -> future occupancy, triplanes and ego trajectory.

    ``layout`` keys (:class:`~t3fast.forecast.pipeline.Layout`: ``ego_aligned``,
    ``static_from_present``, ``render_agents``, ``agent_boxes``) fix how it forecasts. The encoder
    is frozen (stage 2 trains the forecaster and planner and fine-tunes the decoder); it stays in
    eval mode whatever ``train()`` is called with.
    """

    def __init__(self, encoder: TriplaneEncoder, forecaster: DeltaTriplaneForecaster | FlowTriplaneForecaster,
                 planner: MotionPlanner | RoutePlanner, decoder: TriplaneDecoder,
                 box_motion: BoxMotionNet | None = None, **layout: bool):
        super().__init__()
        self.encoder, self.forecaster, self.planner, self.decoder = encoder, forecaster, planner, decoder
        self.box_motion, self.layout = box_motion, Layout(**layout)
        check_layout(self.layout, forecaster, box_motion)
        self.encoder.requires_grad_(False)
        # the sizes it was built from (set by from_config): what a checkpoint records
        self.autoencoder_config: AutoencoderConfig | None = None
        self.world_config: WorldModelConfig | None = None
        self._compiled: Callable[..., Forecast] | None = None  # compile_forecast

    @classmethod
    def from_config(cls, autoencoder: AutoencoderConfig, world: WorldModelConfig) -> T3Former:
        """A world model of the given sizes (untrained; load a stage-1 encoder/decoder into it)."""
        bev = autoencoder.latent == "bev"
        forecaster = FlowTriplaneForecaster(
            channels=autoencoder.channels, plane_shape=autoencoder.plane_shape, widths=world.flow_widths,
            history=world.history, steps=world.steps, flow_scale=world.flow_scale, match_radius=world.match_radius,
            bev=bev,
        ) if world.forecaster == "flow" else DeltaTriplaneForecaster(
            channels=autoencoder.channels, plane_shape=autoencoder.plane_shape,
            widths=world.forecaster_widths[: world.scales], history=world.history, steps=world.steps,
            heads=world.forecaster_heads, layers=world.forecaster_layers, max_tokens=world.max_tokens,
            predict_delta=world.predict_delta, bev=bev,
        )
        planner = RoutePlanner.from_config(autoencoder, world) if world.planner == "route" else MotionPlanner(
            channels=autoencoder.channels, widths=world.planner_widths, d_act=world.d_act, steps=world.steps,
            past=world.past_actions, heads=world.planner_heads, layers=world.planner_layers, bev=bev,
        )
        model = cls(TriplaneEncoder(autoencoder), forecaster, planner, TriplaneDecoder.from_config(autoencoder),
                    BoxMotionNet(world.history, world.steps) if world.box_motion else None,
                    ego_aligned=world.ego_aligned, static_from_present=world.static_from_present,
                    render_agents=world.render_agents, agent_boxes=world.agent_boxes)
        model.autoencoder_config, model.world_config = autoencoder, world
        return model

    @property
    def reads_command(self) -> bool:
        """Whether the planner reads a route command (:class:`~t3fast.models.route_planner.RoutePlanner`)."""
        return isinstance(self.planner, RoutePlanner)

    @property
    def ego_aligned(self) -> bool:
        """Whether it forecasts in the present ego frame (:class:`~t3fast.forecast.pipeline.Layout`)."""
        return self.layout.ego_aligned

    # the layout's keys, read as the model's own (the rows of the evaluation table name them)
    static_from_present = property(lambda self: self.layout.static_from_present, doc=Layout.__doc__)
    render_agents = property(lambda self: self.layout.render_agents, doc=Layout.__doc__)
    agent_boxes = property(lambda self: self.layout.agent_boxes, doc=Layout.__doc__)

    @property
    def pipeline(self) -> ForecastPipeline:
        """The stages of its forecast (:mod:`t3fast.forecast`), over its networks as they are now."""
        return build_pipeline(self.layout, self.encoder, self.forecaster, self.planner, self.decoder,
                              self.box_motion)

    def train(self, mode: bool = True) -> T3Former:
        super().train(mode)
        self.encoder.eval()
        return self

    def encode_sequence(self, occupancy: Tensor) -> Triplane:
        """Labels ``[B, T, X, Y, Z]`` -> triplane planes ``[B, T, C, H, W]`` (frozen encoder)."""
        return encode_sequence(self.encoder, occupancy)

    @torch.no_grad()
    def forecast(
        self, past_occupancy: Tensor, past_motion: Tensor, future_actions: Tensor | None = None, steps: int = 6,
        command: Tensor | None = None,
    ) -> Forecast:
        """The full forecasting step.

        Args:
            past_occupancy: labels ``[B, T, X, Y, Z]`` of the past frames and the present (last),
                each in its own ego frame.
            past_motion: ego -> world poses ``[B, T, 4, 4]`` of those frames, or the past
                displacements ``[B, T - 1, 2]`` in the present frame.
            future_actions: ``[B, S, 2]`` displacements (or ``[B, S, 3]`` poses x, y, yaw) in
                the present frame to forecast along (the world model as a simulator); None:
                the planner plans them.
            steps: future frames (6 = 3 s at 2 Hz); ``future_actions`` sets it when given.
            command: route commands int64 ``[B]`` (turn right / left / go straight,
                :mod:`t3fast.data.route`) for a planner that reads them (``planner="route"``);
                None plans without one. Unused when ``future_actions`` are given.

        Raises :class:`~t3fast.errors.UsageError` (a ``ValueError``), before any frame is
        encoded, for: arguments that are not tensors of the documented shapes, an empty batch, a
        number of past frames other than the model's ``history``, NaN or infinite poses,
        displacements or ``future_actions`` (naming the first index), poses that are not rigid
        motions, motion beyond what a vehicle does (a step over 100 m between frames, a pose
        over 1e7 m from the world origin: :mod:`~t3fast.models.forecast_inputs`), integer
        motion (to plan with the autoregressive planner: motion of another dtype than its
        weights), more future steps than the model forecasts (naming its maximum), and an input
        on another device than the model's weights (the forecast runs where they are).
        """
        check_past_occupancy(past_occupancy, self.encoder.config.grid)
        b, t = past_occupancy.shape[:2]
        if t != self.forecaster.history:  # it would run, on inputs it never saw
            raise UsageError(f"past_occupancy has {t} past frames (the present included), but this model was "
                             f"trained on {self.forecaster.history} (world_config.history)")
        check_devices(next(self.parameters()).device, past_occupancy=past_occupancy, past_motion=past_motion,
                      future_actions=future_actions, command=command)
        with read_together():  # the values: one host synchronisation
            check_class_ids(past_occupancy, self.encoder.config.num_classes)
            check_past_motion(past_motion, b, t)
            check_plan(self.forecaster, self.planner, steps, future_actions, command, past_motion)
        return (self._compiled or self.pipeline)(past_occupancy, past_motion, future_actions, steps, command)

    def compile_forecast(self, **options: Any) -> T3Former:
        """Compile :meth:`forecast` after its input checks into one graph
        (:func:`~t3fast.forecast.compiled.compiled_forecast`: ``torch.compile`` with ``options``,
        on CUDA one CUDA graph); call it once the model is on its device. The forecasts are the
        eager ones; every shipped layout traces whole. For a GPU: it runs the fixed-size code a
        GPU needs (:func:`~t3fast.host_syncs.sync_free`), which on the CPU takes 1.7x the eager
        forecast's time. Returns the model."""
        self._compiled = compiled_forecast(self.pipeline, next(self.parameters()).device, **options)
        return self
