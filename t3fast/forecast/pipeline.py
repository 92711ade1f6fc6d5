"""The forecast's stages, chosen once from a world model's layout and networks, run in order.

encode -> agents -> scene forecast -> agents' motion -> plan -> render (see :mod:`t3fast.forecast`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import Tensor, nn

from t3fast.errors import ConfigError
from t3fast.forecast.agents import FindAgents
from t3fast.forecast.encode import EncodePast
from t3fast.forecast.motion import MoveAgents
from t3fast.forecast.plan import PhiActPlan, RoutePlan, given_plan
from t3fast.forecast.records import AgentMoves, Forecast, Past, Plan, Scene
from t3fast.forecast.render import DecodeFrames, DrawAgents, KeepObservedStatic
from t3fast.forecast.scene import DeltaScene, FlowScene
from t3fast.models.box_motion import BoxMotionNet
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.route_planner import RoutePlanner

Render = Callable[[Past, Scene, "list[AgentMoves] | None", Tensor], Tensor]


@dataclass(frozen=True)
class Layout:
    """How a world model forecasts, beyond its networks (the keys of
    :class:`~t3fast.models.config.WorldModelConfig` of the same names).

    Attributes:
        ego_aligned: forecast in the present ego frame (the past moved there with its poses),
            each future frame decoded in the ego frame of its pose; False: the papers'
            formulation, every frame in its own ego frame.
        static_from_present: an ego-aligned forecast keeps the observed present's static world
            (:func:`~t3fast.forecast.render.observed_static`); False: decoded frames only.
        render_agents: draw the observed agents moved along the flow forecaster's displacements
            (label space) instead of decoding them.
        agent_boxes: draw those agents as the boxes fitted to their past frames.
    """

    ego_aligned: bool = False
    static_from_present: bool = True
    render_agents: bool = False
    agent_boxes: bool = False


@dataclass
class ForecastPipeline:
    """The stages of one world model's forecast; ``motion`` is None where no agent is drawn."""

    encode: EncodePast
    agents: FindAgents
    scene: FlowScene | DeltaScene
    motion: MoveAgents | None
    plan: RoutePlan | PhiActPlan
    render: Render

    def __call__(self, past_occupancy: Tensor, past_motion: Tensor, future_actions: Tensor | None, steps: int,
                 command: Tensor | None) -> Forecast:
        """The forecast of ``steps`` future frames (the length of ``future_actions`` when given,
        then the plan is theirs); the arguments as for
        :meth:`~t3fast.models.world_model.T3Former.forecast`, already checked."""
        return self.from_past(self.encode(past_occupancy, past_motion), future_actions, steps, command)

    def from_past(self, past: Past, future_actions: Tensor | None, steps: int, command: Tensor | None) -> Forecast:
        """The forecast from an encoded :class:`Past` (a streaming user encodes each new frame
        once and keeps the planes of the earlier ones)."""
        agents = self.agents(past)
        scene = self.scene(past, agents, steps if future_actions is None else future_actions.shape[1])
        moves = self.motion(past, agents, scene) if self.motion is not None else None
        plan: Plan = self.plan(past, scene, command) if future_actions is None else given_plan(future_actions)
        labels = self.render(past, scene, moves, plan.poses)
        return Forecast(labels, scene.futures, plan.actions, plan.actions.cumsum(1), plan.poses)


def check_layout(layout: Layout, forecaster: nn.Module, box_motion: BoxMotionNet | None) -> None:
    """A layout that the networks can forecast with: drawn agents need the flow forecaster's
    displacements, boxes need drawn agents, a box motion network needs boxes."""
    if layout.render_agents and not isinstance(forecaster, FlowTriplaneForecaster):
        raise ConfigError("render_agents draws the agents along the flow forecaster's displacements: "
                          "it needs forecaster='flow'")
    if layout.agent_boxes and not layout.render_agents:
        raise ConfigError("agent_boxes draws the agents render_agents moves as fitted boxes: it needs render_agents")
    if box_motion is not None and not layout.agent_boxes:
        raise ConfigError("box_motion moves the fitted boxes agent_boxes draws: it needs agent_boxes")


def build_pipeline(layout: Layout, encoder: TriplaneEncoder, forecaster: nn.Module, planner: nn.Module,
                   decoder: TriplaneDecoder, box_motion: BoxMotionNet | None) -> ForecastPipeline:
    """The stages of a world model with these networks and ``layout``."""
    check_layout(layout, forecaster, box_motion)
    flow = isinstance(forecaster, FlowTriplaneForecaster)
    render = choose_render(layout, decoder)
    return ForecastPipeline(
        encode=EncodePast(encoder, layout.ego_aligned),
        agents=FindAgents(encoder.config.plane_shape[:2], flow, layout.agent_boxes),
        scene=FlowScene(forecaster) if flow else DeltaScene(forecaster),
        motion=MoveAgents(box_motion) if isinstance(render, DrawAgents) else None,
        plan=RoutePlan(planner) if isinstance(planner, RoutePlanner) else PhiActPlan(planner),
        render=render,
    )


def choose_render(layout: Layout, decoder: TriplaneDecoder) -> Render:
    """The renderer of ``layout``: agents drawn, the observed static world kept, or decoded frames."""
    if not (layout.ego_aligned and layout.static_from_present):
        return DecodeFrames(decoder, layout.ego_aligned)
    return DrawAgents(decoder) if layout.render_agents else KeepObservedStatic(decoder)
