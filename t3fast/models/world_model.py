"""T3Former: the world model wiring encoder (frozen), forecaster, planner and decoder.

Ego motion is geometry (``ego_aligned=True``, see :mod:`t3fast.models.ego_motion`): the past
frames are moved into the present ego frame with the past poses before encoding, the
forecaster predicts the triplanes of future steps in that one frame (static content stays
still; Delta carries what moves), and each future frame is decoded in its own ego
coordinates by querying the predicted triplane at that frame's voxel centres, placed with the
pose the planner plans (position; heading = direction of travel) or the one given
(``future_actions``: a steered forecast); each future frame is the present frame moved with
the ego, edited where the forecast moves agents (``static_from_present``,
:func:`observed_static`), so the latent's job is what moves and what comes into view.
``ego_aligned=False`` is the papers' formulation: every frame in its own ego frame, the
forecaster left to learn the ego's motion."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from t3fast.agents.box_kinematics import ego_step
from t3fast.agents.boxes import AgentBoxes, draw_agent_boxes, fit_agent_boxes
from t3fast.agents.tracker import component_shifts, frame_agents, move_agents, tracker_velocities
from t3fast.data.classes import AGENT_CLASSES, FLAT_GROUND_CLASSES, FREE, IGNORE, VOXEL_SIZE
from t3fast.errors import UsageError
from t3fast.models.box_motion import BoxMotionNet, predict_box_poses
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.ego_motion import (
    displacements_from_poses,
    extrapolate_poses,
    frame_queries,
    planar_poses,
    poses_from_displacements,
    unwarp_sequence,
    warp_sequence,
)
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.forecast_inputs import (
    check_command,
    check_finite,
    check_future_actions,
    check_horizon,
    check_past_motion,
    check_past_occupancy,
    check_planner_dtype,
    check_steps,
    steps_into,
    supported_steps,
)
from t3fast.models.forecaster import DeltaTriplaneForecaster
from t3fast.models.planner import MotionPlanner, constant_turn_rate
from t3fast.models.route_planner import RoutePlanner
from t3fast.models.triplane import Triplane


@dataclass
class Forecast:
    """What :meth:`T3Former.forecast` returns for ``S`` future steps.

    Attributes:
        labels: uint8 ``[B, S, X, Y, Z]`` decoded future occupancy (argmax mode).
        triplanes: per step the predicted :class:`Triplane` (planes ``[B, C, H, W]``).
        actions: ``[B, S, 2]`` planned (or given) displacements in the present frame.
        trajectory: ``[B, S, 2]`` planned positions, ``actions.cumsum(1)``.
        poses: ``[B, S, 3]`` future ego poses (x, y, yaw) in the present frame; each labels
            frame is in the ego frame of its pose.
    """

    labels: Tensor
    triplanes: list[Triplane]
    actions: Tensor
    trajectory: Tensor
    poses: Tensor


_AGENTS = torch.tensor(AGENT_CLASSES)
_GROUND = torch.tensor(FLAT_GROUND_CLASSES)


def present_in_frames(present: Tensor, poses: Tensor) -> Tensor:
    """The present frame's labels ``[B, X, Y, Z]`` moved into the ego frame of each future pose
    ``poses`` ``[B, S, 3]``: ``[B, S, X, Y, Z]``, ``IGNORE`` where a frame looks beyond the
    present grid."""
    return unwarp_sequence(present.unsqueeze(1).expand(-1, poses.shape[1], *present.shape[1:]), poses, fill=IGNORE)


def observed_static(decoded: Tensor, reference: Tensor, moved: Tensor) -> Tensor:
    """Future frames as the observed present edited where the forecast moves agents.

    The static world does not change in 3 s, and the latent loses detail (thin walls, trunks,
    small cars), so each future frame starts from the present frame's labels moved into its
    ego frame, ``moved`` ``[B, S, X, Y, Z]`` (:func:`present_in_frames`). The forecast
    ``decoded`` ``[B, S, X, Y, Z]`` edits it only where it differs from ``reference`` (the present
    triplane decoded at the same voxels: what the latent shows with no change), the change
    involves an agent class (vehicles and humans move), and the observed voxel is free or an
    agent (agents do not move into walls or the ground). With no predicted change the result is
    the present frame moved with the ego, exactly. Beyond the present grid nothing was
    observed: there the forecast's continuation of its edge is kept for flat ground (roads and
    sidewalks go on) and everything else is free (continuing walls, trees and cars past the
    edge cost 6.5 IoU points on validation windows; ground alone gained 1.6).
    """
    agents = _AGENTS.to(decoded.device)
    agent_change = (decoded != reference) & (torch.isin(decoded, agents) | torch.isin(reference, agents))
    editable = torch.isin(moved, agents) | (moved == FREE)
    inside = torch.where(agent_change & editable, decoded, moved)
    return torch.where(moved == IGNORE, beyond_present(decoded), inside)


def beyond_present(decoded: Tensor) -> Tensor:
    """What a forecast shows beyond the observed present grid: its decoded flat ground (roads
    and sidewalks go on), everything else free."""
    return torch.where(torch.isin(decoded, _GROUND.to(decoded.device)), decoded, torch.full_like(decoded, FREE))


def planned_poses(
    actions: Tensor, past_actions: Tensor, past_poses: Tensor | None = None, min_step: float = 0.2
) -> Tensor:
    """Future poses ``[B, S, 3]`` for planned displacements ``actions`` ``[B, S, 2]``: positions
    are their cumulative sum. Headings continue the observed yaw rate of the past poses
    ``[B, T, 3]`` (:func:`extrapolate_poses`), each turned by the angle between the planned
    displacement and that of constant speed and turn rate (:func:`constant_turn_rate` of
    ``past_actions``) where both move at least ``min_step`` metres (slower, a direction is
    noise: a 5 cm correction to a standing ego would swing its heading anywhere). A heading
    read from positions alone is noisier (0.6 degrees mean error one step ahead on validation
    windows, against 0.3 from the past yaw rate). Without past poses, the direction of travel."""
    if past_poses is None:
        return poses_from_displacements(actions)
    steps = actions.shape[1]
    base = constant_turn_rate(past_actions, steps)
    cross = base[..., 0] * actions[..., 1] - base[..., 1] * actions[..., 0]
    turn = torch.atan2(cross, (base * actions).sum(-1))
    moving = (base.norm(dim=-1) >= min_step) & (actions.norm(dim=-1) >= min_step)
    heading = extrapolate_poses(past_poses, steps)[..., 2] + torch.where(moving, turn, torch.zeros_like(turn))
    return torch.cat([actions.cumsum(1), heading.unsqueeze(-1)], dim=-1)


def split_past_motion(motion: Tensor) -> tuple[Tensor, Tensor]:
    """Past planar poses ``[B, T, 3]`` (present frame, present last) and displacements
    ``[B, T - 1, 2]`` from either ego -> world poses ``[B, T, 4, 4]`` or past displacements
    ``[B, T - 1, 2]`` (then each past heading is taken as the direction of travel)."""
    if motion.dim() == 4 and motion.shape[-2:] == (4, 4):
        poses = planar_poses(motion, motion.shape[1] - 1)
        return poses, poses[:, 1:, :2] - poses[:, :-1, :2]
    if motion.dim() != 3 or motion.shape[-1] != 2:
        raise ValueError(f"past motion must be poses [B, T, 4, 4] or displacements [B, T-1, 2], "
                         f"got shape {list(motion.shape)}")
    # positions of the past frames: the present at the origin, each earlier one a step back
    back = torch.flip(torch.flip(motion, [1]).cumsum(1), [1])
    xy = torch.cat([-back, torch.zeros_like(motion[:, :1])], dim=1)
    heading = torch.atan2(motion[..., 1], motion[..., 0])
    heading = torch.cat([heading[:, :1], heading], dim=1) - heading[:, -1:]  # the present heads along +x
    return torch.cat([xy, heading.unsqueeze(-1)], dim=-1), motion


class T3Former(nn.Module):
    """Past occupancy and motion -> future occupancy, triplanes and ego trajectory.

    The encoder is frozen (stage 2 trains the forecaster and planner and fine-tunes the
    decoder); it stays in eval mode whatever ``train()`` is called with.
    """

    def __init__(
        self,
        encoder: TriplaneEncoder,
        forecaster: DeltaTriplaneForecaster | FlowTriplaneForecaster,
        planner: MotionPlanner | RoutePlanner,
        decoder: TriplaneDecoder,
        ego_aligned: bool = False,
        static_from_present: bool = True,
        render_agents: bool = False,
        agent_boxes: bool = False,
        box_motion: BoxMotionNet | None = None,
    ):
        super().__init__()
        self.encoder, self.forecaster, self.planner, self.decoder = encoder, forecaster, planner, decoder
        self.ego_aligned, self.static_from_present = ego_aligned, static_from_present
        if render_agents and not isinstance(forecaster, FlowTriplaneForecaster):
            raise ValueError("render_agents draws the agents along the flow forecaster's displacements: "
                             "it needs forecaster='flow'")
        if agent_boxes and not render_agents:
            raise ValueError("agent_boxes draws the agents render_agents moves as fitted boxes: it needs render_agents")
        if box_motion is not None and not agent_boxes:
            raise ValueError("box_motion moves the fitted boxes agent_boxes draws: it needs agent_boxes")
        self.render_agents, self.agent_boxes, self.box_motion = render_agents, agent_boxes, box_motion
        self.encoder.requires_grad_(False)
        # the sizes it was built from (set by from_config): what a checkpoint records
        self.autoencoder_config: AutoencoderConfig | None = None
        self.world_config: WorldModelConfig | None = None

    @classmethod
    def from_config(cls, autoencoder: AutoencoderConfig, world: WorldModelConfig) -> T3Former:
        """A world model of the given sizes (untrained; load a stage-1 encoder/decoder into it)."""
        bev = autoencoder.latent == "bev"
        forecaster = FlowTriplaneForecaster(
            channels=autoencoder.channels,
            plane_shape=autoencoder.plane_shape,
            widths=world.flow_widths,
            history=world.history,
            steps=world.steps,
            flow_scale=world.flow_scale,
            match_radius=world.match_radius,
            bev=bev,
            tracker_prior=world.tracker_prior,
            motion_context=world.motion_context,
        ) if world.forecaster == "flow" else DeltaTriplaneForecaster(
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
        planner = RoutePlanner.from_config(autoencoder, world) if world.planner == "route" else MotionPlanner(
            channels=autoencoder.channels,
            widths=world.planner_widths,
            d_act=world.d_act,
            steps=world.steps,
            past=world.past_actions,
            heads=world.planner_heads,
            layers=world.planner_layers,
            bev=bev,
        )
        model = cls(TriplaneEncoder(autoencoder), forecaster, planner, TriplaneDecoder.from_config(autoencoder),
                    ego_aligned=world.ego_aligned, static_from_present=world.static_from_present,
                    render_agents=world.render_agents, agent_boxes=world.agent_boxes,
                    box_motion=BoxMotionNet(world.history, world.steps) if world.box_motion else None)
        model.autoencoder_config, model.world_config = autoencoder, world
        return model

    @property
    def reads_command(self) -> bool:
        """Whether the planner reads a route command (:class:`~t3fast.models.route_planner.RoutePlanner`)."""
        return isinstance(self.planner, RoutePlanner)

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

    @torch.no_grad()
    def encode_history(self, occupancy: Tensor, poses: Tensor) -> Triplane:
        """Past frames ``[B, T, X, Y, Z]`` (the present last) -> planes ``[B, T, C, H, W]`` in the
        frame the forecaster works in: with ``ego_aligned`` every frame is first moved into the
        present ego frame with its planar pose ``poses`` ``[B, T, 3]`` there."""
        if self.ego_aligned:
            occupancy = warp_sequence(occupancy, poses)
        return self.encode_sequence(occupancy)

    @torch.no_grad()
    def agent_velocity(self, occupancy: Tensor, poses: Tensor) -> Tensor | None:
        """The agents' velocities a forecaster with a tracker prior starts from
        (:func:`~t3fast.agents.tracker.tracker_velocities`, ``[B, 4, H, W]`` plane cells
        per step), measured in the last three past frames ``occupancy[:, -3:]`` (labels
        ``[B, T, X, Y, Z]``) moved into the present frame with ``poses`` ``[B, T, 3]``; None for a
        forecaster without one."""
        if not getattr(self.forecaster, "tracker_prior", False):
            return None
        frames = torch.cat([warp_sequence(occupancy[:, -3:-1], poses[:, -3:-1]), occupancy[:, -1:]], dim=1)
        return tracker_velocities(frames, self.encoder.config.plane_shape[:2])

    @torch.no_grad()
    def fit_boxes(self, occupancy: Tensor, poses: Tensor) -> list[AgentBoxes] | None:
        """Per sample, the boxes of the present's agents fitted to the past frames
        (:func:`~t3fast.agents.boxes.fit_agent_boxes`; labels ``[B, T, X, Y, Z]``, each in its
        own ego frame, planar poses ``[B, T, 3]`` in the present frame), what :meth:`render`
        draws them with, and with a :attr:`box_motion` network where it moves them
        (``AgentBoxes.future``); None for a model that does not draw boxes."""
        if not self.agent_boxes:
            return None
        fits = []
        for n in range(occupancy.shape[0]):
            now, fit = fit_agent_boxes(occupancy[n], poses[n])
            if self.box_motion is not None:
                fit.future = predict_box_poses(self.box_motion, occupancy[n, -1], fit, now["ids"],
                                               ego_step(poses[n].cpu()))
            fits.append(fit)
        return fits

    @torch.no_grad()
    def decode_frames(self, futures: list[Triplane], poses: Tensor) -> Tensor:
        """Future triplanes -> labels uint8 ``[B, S, X, Y, Z]``, each frame in the ego frame of
        its pose ``poses[:, k]`` (``[B, S, 3]`` in the present frame; ``ego_aligned`` only)."""
        if not self.ego_aligned:
            return torch.stack([self.decoder.predict(t) for t in futures], dim=1)
        grid = self.decoder.grid
        frames = []
        for k, t in enumerate(futures):
            points = frame_queries(poses[:, k].float(), grid)
            frames.append(self.decoder.predict(t, points).view(-1, *grid))
        return torch.stack(frames, dim=1)
    @torch.no_grad()
    def reference_frames(self, present_planes: Triplane, decoded: Tensor, moved: Tensor, poses: Tensor) -> Tensor:
        """The present triplane (planes ``[B, C, H, W]``) decoded at the voxels of each future
        frame (``decoded`` ``[B, S, X, Y, Z]``, poses ``[B, S, 3]``) where the forecast or the
        present moved into that frame (``moved``, :func:`present_in_frames`) show an agent: the
        only voxels where :func:`observed_static` can take a forecast label that differs from
        the observed one. Elsewhere ``decoded`` itself (no change), so only ~2 % of the voxels
        are decoded twice."""
        reference = torch.empty_like(decoded)
        for b in range(decoded.shape[0]):
            planes = present_planes.map(lambda p, b=b: p[b : b + 1])
            for k in range(decoded.shape[1]):
                points = frame_queries(poses[b : b + 1, k].float(), self.decoder.grid)
                reference[b, k] = self._present_where_agents(planes, points, decoded[b, k].flatten(),
                                                             moved[b, k].flatten()).view(decoded.shape[2:])
        return reference

    def _present_where_agents(self, planes: Triplane, points: Tensor, decoded: Tensor, observed: Tensor) -> Tensor:
        """The reference of :func:`observed_static` for one frame's voxels: their forecast labels
        ``decoded`` ``[N]``, except where those or the observed labels ``observed`` ``[N]`` show an
        agent, where the present triplane ``planes`` (batch 1) is decoded at ``points``
        ``[1, N, 3]`` instead."""
        agents = _AGENTS.to(decoded.device)
        need = torch.isin(decoded, agents) | torch.isin(observed, agents)
        reference = decoded.clone()
        if bool(need.any()):
            reference[need] = self.decoder.predict(planes, points[:, need]).view(-1)
        return reference

    def _forecaster(self, past: Triplane, steps: int, first_step: int = 0, velocity: Tensor | None = None
                    ) -> tuple[list[Triplane], list[Triplane], Tensor | None]:
        """(future triplanes, their changes, the flow forecaster's forward displacements of the
        present cells ``[B, steps, 2, H, W]`` or None)."""
        if isinstance(self.forecaster, FlowTriplaneForecaster):
            return self.forecaster(past, steps, first_step, velocity, motion=True)
        return (*self.forecaster(past, steps, first_step), None)

    def rollout(
        self, past: Triplane, past_actions: Tensor, steps: int, first_step: int = 0, velocity: Tensor | None = None,
        command: Tensor | None = None,
    ) -> tuple[list[Triplane], list[Triplane], Tensor, Tensor | None]:
        """Future triplanes, their changes, displacements ``[B, steps, 2]`` (differentiable), and
        the flow forecaster's forward displacements of the present xy cells ``[B, steps, 2, H, W]``
        (plane cells; None for the Delta forecaster).

        Args:
            past: planes ``[B, T, C, H, W]`` of the frames before future step ``first_step``.
            past_actions: ``[B, T_p + first_step, 2]`` displacements so far (present frame).
            velocity: the agents' velocities of :meth:`agent_velocity` (forecasters with a
                tracker prior need them).
            command: route commands int64 ``[B]`` (:mod:`t3fast.data.route`) for a planner that
                reads them (:class:`~t3fast.models.route_planner.RoutePlanner`); None: none given.
        """
        futures, deltas, motion = self._forecaster(past, steps, first_step, velocity)
        present = past.map(lambda p: p[:, -1])
        if isinstance(self.planner, RoutePlanner):
            if first_step != 0:
                raise ValueError(f"the route planner plans every step from the present, not from step {first_step}")
            actions = self.planner(past.xy[:, -1], past.xy[:, -2], past_actions, command)[:, :steps]
            return futures, deltas, actions, motion
        # The planning loss does not reach the forecaster: its gradient through the predicted
        # triplanes competes with the triplane loss and stalls forecasting (see the tests).
        plan_in = [[t.map(torch.Tensor.detach) for t in ts] for ts in (futures, deltas)]
        actions = self.planner(present, plan_in[0], plan_in[1], past_actions, first_step)
        return futures, deltas, actions, motion

    def forward(
        self, past: Triplane | None, past_actions: Tensor | None, steps: int = 6, first_step: int = 0,
        points: list[Tensor] | None = None, motion: bool = False, velocity: Tensor | None = None,
        plan_from: tuple[Tensor, Tensor, Tensor, Tensor] | None = None,
        motion_from: tuple[Tensor, Tensor, Tensor] | None = None,
        boxes_from: tuple[Tensor, Tensor] | None = None,
    ) -> (tuple[list[Triplane], Tensor, list[Tensor] | None] | tuple[list[Triplane], Tensor, Tensor, Tensor | None]
          | tuple[Tensor, Tensor] | Tensor):
        """Training rollout: :meth:`rollout` plus decoder logits ``[B, N, K]`` of each future
        triplane at ``points[k]`` ``[B, N, 3]`` (one forward call, so DDP sees one graph).

        Returns (future triplanes, displacements ``[B, steps, 2]``, logits or None). With
        ``motion`` (the flow forecaster), instead its
        :meth:`~t3fast.models.flow_forecaster.FlowTriplaneForecaster.predict`: (future
        triplanes, forward displacements of the present cells ``[B, S, 2, H, W]``, Deltas
        ``[B, S, C, H, W]``) and the route planner's displacements ``[B, S, 2]`` for the inputs
        ``plan_from`` (present and previous xy planes, past displacements, commands: see
        :class:`~t3fast.models.route_planner.RoutePlanner`; they may be other windows than the
        forecaster's), else None. ``velocity``: as for :meth:`rollout`.

        With ``past`` None, only the route planner's candidate plans and their scores for
        ``plan_from`` (:meth:`RoutePlanner.candidates`; the planner trained on its own,
        :mod:`t3fast.training.planner`). With ``past`` None and ``motion_from`` (the tracker's
        velocities ``[B, 4, H, W]``, the present and previous xy planes ``[B, C, H, W]``), only the
        flow forecaster's displacements of the tracked agents ``[B, S, 2, H, W]``
        (:meth:`~t3fast.models.flow_forecaster.FlowTriplaneForecaster.tracked_motion`; the motion
        head trained on its own, :mod:`t3fast.training.motion`). With ``past`` None and
        ``boxes_from`` (agents' views ``[n, C, A, W]`` and kinematics ``[n, F]``), only the box
        motion network's corrections ``[n, S, 3]`` (:class:`~t3fast.models.box_motion.BoxMotionNet`,
        trained on its own: :mod:`t3fast.training.box_motion`).
        """
        if past is None and boxes_from is not None:
            if self.box_motion is None:
                raise ValueError("boxes_from is the box motion network's input: it needs world_config.box_motion")
            return self.box_motion(*boxes_from)
        if past is None and motion_from is not None:
            if not getattr(self.forecaster, "tracker_prior", False):
                raise ValueError("motion_from is the motion head's input: it needs the flow forecaster with "
                                 "world_config.tracker_prior = True")
            return self.forecaster.tracked_motion(*motion_from)
        if past is None:
            if plan_from is None or not self.reads_command:
                raise ValueError("without past planes the forward pass is the route planner's alone: it needs "
                                 "plan_from and world_config.planner = 'route'")
            return self.planner.candidates(*plan_from)
        if motion:
            if not isinstance(self.forecaster, FlowTriplaneForecaster):
                raise ValueError("motion=True needs the flow forecaster (world_config.forecaster = 'flow')")
            if plan_from is not None and not self.reads_command:
                raise ValueError("plan_from is the route planner's input: it needs world_config.planner = 'route'")
            actions = None if plan_from is None else self.planner(*plan_from)
            return (*self.forecaster.predict(past, velocity), actions)
        futures, _, actions, _ = self.rollout(past, past_actions, steps, first_step, velocity)
        logits = None if points is None else [self.decoder(t, p) for t, p in zip(futures, points)]
        return futures, actions, logits

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
        weights), and more future steps than the model forecasts (naming its maximum).
        """
        check_past_occupancy(past_occupancy, self.encoder.config.grid)
        b, t = past_occupancy.shape[:2]
        self._check_history("past_occupancy", t)
        check_past_motion(past_motion, b, t)
        self._check_plan(b, t - 1, steps, future_actions, command, "past_motion", past_motion)
        poses, actions = split_past_motion(past_motion)
        past = self.encode_history(past_occupancy, poses)
        return self.forecast_from_triplanes(past, actions, steps, future_actions, past_occupancy[:, -1], poses,
                                            self.agent_velocity(past_occupancy, poses), command,
                                            self.fit_boxes(past_occupancy, poses))

    def _check_plan(self, batch: int, past_actions: int, steps: int, future_actions: Tensor | None,
                    command: Tensor | None, motion_name: str, motion: Tensor) -> None:
        """What the forecast is asked to do: ``steps`` planned from the past ``motion`` (argument
        ``motion_name``, ``past_actions`` displacements) or the given ``future_actions``, with
        ``command``."""
        check_command(command, batch, self.reads_command)
        trained = self.forecaster.steps
        if future_actions is None:
            if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
                raise UsageError(f"steps must be a positive integer, got {steps!r}")
            check_planner_dtype(motion_name, motion, self.planner)
            check_horizon(steps, supported_steps(self.forecaster, self.planner, past_actions, True), trained, "steps")
        else:
            check_future_actions(future_actions, batch)
            limit = supported_steps(self.forecaster, self.planner, past_actions, False)
            check_horizon(future_actions.shape[1], limit, trained, "future_actions")

    def _check_history(self, name: str, frames: int) -> None:
        """The forecaster was trained on ``history`` past frames (the present included); fewer
        or more would run, on inputs it never saw."""
        history = self.forecaster.history
        if frames != history:
            raise UsageError(f"{name} has {frames} past frames (the present included), but this model was "
                             f"trained on {history} (world_config.history)")

    @torch.no_grad()
    def forecast_from_triplanes(
        self, past: Triplane, past_actions: Tensor, steps: int = 6, future_actions: Tensor | None = None,
        present: Tensor | None = None, past_poses: Tensor | None = None, velocity: Tensor | None = None,
        command: Tensor | None = None, boxes: list[AgentBoxes] | None = None,
    ) -> Forecast:
        """The forecasting step from encoded past frames (planes ``[B, T, C, H, W]`` from
        :meth:`encode_history`): forecaster, planner (unless ``future_actions`` are given) and
        decoding to labels. A streaming user encodes each new frame once (papers'
        formulation) and keeps the planes of the previous ones. ``present``: the present
        frame's labels ``[B, X, Y, Z]``, for :func:`observed_static`; ``past_poses``: the past
        planar poses ``[B, T, 3]``, for the planned headings (:func:`planned_poses`);
        ``velocity``: the agents' velocities (:meth:`agent_velocity`) for a forecaster with a
        tracker prior; ``command``: as for :meth:`forecast`; ``boxes``: the agents' fitted boxes
        (:meth:`fit_boxes`) for a model that draws them.
        Refuses (:class:`~t3fast.errors.UsageError`) a number of past frames ``T`` other
        than the model's ``history``, non-finite or unbounded motion and more future steps
        than the model forecasts, as :meth:`forecast` does."""
        self._check_history("past", past.xy.shape[1])
        check_steps("past_actions", past_actions)
        if past_poses is not None:
            check_finite("past_poses", past_poses)
            check_steps("past_poses", steps_into(past_poses[..., :2], past_poses[:, :1, :2]),
                        " (from the frame before it)")
        self._check_plan(past.xy.shape[0], past_actions.shape[1], steps, future_actions, command,
                         "past_actions", past_actions)
        if future_actions is None:
            futures, _, actions, motion = self.rollout(past, past_actions, steps, velocity=velocity, command=command)
            poses = planned_poses(actions, past_actions, past_poses)
        else:
            futures, _, motion = self._forecaster(past, future_actions.shape[1], velocity=velocity)
            if future_actions.shape[-1] == 3:  # given as poses
                poses, actions = future_actions, displacements_from_poses(future_actions)
            else:
                actions, poses = future_actions, poses_from_displacements(future_actions)
        labels = self.render(futures, poses, past.map(lambda p: p[:, -1]), present, motion=motion, boxes=boxes)
        return Forecast(labels, futures, actions, actions.cumsum(1), poses)

    @torch.no_grad()
    def render(
        self, futures: list[Triplane], poses: Tensor, present_planes: Triplane, present: Tensor | None = None,
        decoded: Tensor | None = None, motion: Tensor | None = None, boxes: list[AgentBoxes] | None = None,
    ) -> Tensor:
        """Future triplanes -> labels uint8 ``[B, S, X, Y, Z]``, each frame in the ego frame of
        its pose (``poses`` ``[B, S, 3]``): :meth:`decode_frames` (or ``decoded``, its result
        when already at hand) and, given the present frame's labels ``present``
        ``[B, X, Y, Z]`` (ego-aligned, ``static_from_present``), the observed present edited by
        the forecast (:func:`observed_static`; ``present_planes``: the present triplane). A
        model with ``render_agents`` given the forecaster's displacements ``motion``
        ``[B, S, 2, H, W]`` draws the observed agents moved along them instead
        (:meth:`_render_agents`), those with a trusted fitted box in ``boxes`` (:meth:`fit_boxes`)
        drawn as it."""
        keep_present = present is not None and self.ego_aligned and self.static_from_present
        if keep_present and self.render_agents and motion is not None:
            return self._render_agents(futures, motion, poses, present, boxes)
        if keep_present and decoded is None:
            return self._render_changes(futures, poses, present_planes, present)
        labels = self.decode_frames(futures, poses) if decoded is None else decoded
        if keep_present:
            moved = present_in_frames(present, poses)
            labels = observed_static(labels, self.reference_frames(present_planes, labels, moved, poses), moved)
        return labels

    def _render_agents(self, futures: list[Triplane], motion: Tensor, poses: Tensor, present: Tensor,
                       boxes: list[AgentBoxes] | None = None) -> Tensor:
        """:meth:`render` in label space: each future frame is the observed present with every
        agent (8-connected BEV component of vehicle and human columns) moved as a whole by the
        mean of the forecast displacement ``motion`` ``[B, S, 2, H, W]`` over its columns, moved
        into the frame's pose; beyond the present grid, the forecast's decoded flat ground
        (:func:`beyond_present`). The forecaster's motion is drawn exactly: no decoding blurs a
        car or loses a pedestrian (the latent render lost 1.1 moving-class mIoU to the tracker
        that moves the same agents this way). With the tracker prior and an untrained motion
        head, the agents move exactly as the tracker moves them. Given their fitted ``boxes``,
        the agents with a trusted fit are drawn as their box moved by the same mean
        displacement, not rounded to cells (:mod:`t3fast.agents.boxes`)."""
        agents = _AGENTS.to(present.device)
        scenes, drawn = [], []
        for n in range(present.shape[0]):
            now = frame_agents(present[n], agents)
            shift = component_shifts(now, motion[n])
            fitted = boxes[n] if boxes is not None else None
            if fitted is not None and fitted.label.shape[0] != now["cls"].shape[0]:
                raise ValueError(f"render: {fitted.label.shape[0]} fitted boxes for the {now['cls'].shape[0]} agents "
                                 "of the present frame: fit them on the same frames (fit_boxes)")
            as_box = fitted.drawn if fitted is not None else torch.zeros(now["cls"].shape[0], dtype=torch.bool)
            voxels = ~as_box.to(present.device)[now["component"]]
            moved = dict(now, ijz=now["ijz"][voxels], label=now["label"][voxels], component=now["component"][voxels])
            scenes.append(move_agents(present[n], moved, shift.round().long(), FREE))
            drawn.append((fitted, as_box, shift))
        labels = unwarp_sequence(torch.stack(scenes), poses, fill=IGNORE)
        for k, future in enumerate(futures):
            points = frame_queries(poses[:, k].float(), self.decoder.grid)
            for n in range(labels.shape[0]):
                frame = labels[n, k].view(-1)
                unseen = (frame == IGNORE).nonzero().squeeze(1)
                if unseen.numel():
                    decoded = self.decoder.predict(future.map(lambda p, n=n: p[n : n + 1]), points[n : n + 1, unseen])
                    frame[unseen] = beyond_present(decoded.view(-1))
        for n, (fitted, as_box, shift) in enumerate(drawn):
            if bool(as_box.any()):
                for k in range(labels.shape[1]):
                    if fitted.future is None:
                        centre = fitted.centre[as_box] + shift[k, as_box.to(shift.device)].cpu() * VOXEL_SIZE
                        yaw = fitted.yaw[as_box]
                    else:
                        centre, yaw = fitted.future[k, as_box, :2], fitted.future[k, as_box, 2]
                    draw_agent_boxes(labels[n, k], centre, yaw, fitted.length[as_box],
                                     fitted.width[as_box], fitted.bottom[as_box], fitted.top[as_box],
                                     fitted.label[as_box], poses[n, k].cpu())
        return labels

    def _render_changes(self, futures: list[Triplane], poses: Tensor, present_planes: Triplane,
                        present: Tensor) -> Tensor:
        """:meth:`render` with the observed present, decoding only the voxels whose labels can
        differ from the present's. Where a future triplane's refined planes (what the decode op
        looks up) equal the present one's at every cell a voxel's lookup reads (the xy cells
        around its column; xz and yz whole), the forecast decodes to exactly what the present
        triplane does, so :func:`observed_static` keeps the observed label there. Only the voxels
        near changed xy cells and those beyond the present grid are decoded; a forecaster that
        moves a few agents and carries xz/yz (the flow forecaster) decodes a few percent of each
        frame. Same labels as decoding all."""
        moved = present_in_frames(present, poses)
        labels = moved.clone()
        b = moved.shape[0]
        grid = self.decoder.grid
        h, w = present_planes.xy.shape[-2:]
        now = self.decoder.features(present_planes)  # what the lookups read: the refined planes
        for k, future in enumerate(futures):
            refined = self.decoder.features(future)
            if not (torch.equal(refined.xz, now.xz) and torch.equal(refined.yz, now.yz)):
                changed = torch.ones(b, h, w, dtype=torch.bool, device=moved.device)  # xz/yz changed: every voxel
            else:  # a lookup reads the 2 x 2 cells around its point: the nearest one's 3 x 3 neighbourhood covers them
                diff = (refined.xy != now.xy).any(1, keepdim=True).float()
                changed = nn.functional.max_pool2d(diff, 3, stride=1, padding=1)[:, 0] > 0
            points = frame_queries(poses[:, k].float(), grid)  # [B, N, 3], normalised
            i = ((points[..., 0] + 1) * h / 2 - 0.5).round().long().clamp(0, h - 1)
            j = ((points[..., 1] + 1) * w / 2 - 0.5).round().long().clamp(0, w - 1)
            observed = moved[:, k].reshape(b, -1)
            need = changed.flatten(1).gather(1, i * w + j) | (observed == IGNORE)
            for n in range(b):
                index = need[n].nonzero().squeeze(1)
                if not index.numel():
                    continue
                query = points[n : n + 1, index]
                decoded = self.decoder.predict(future.map(lambda p, n=n: p[n : n + 1]), query).view(-1)
                reference = self._present_where_agents(present_planes.map(lambda p, n=n: p[n : n + 1]), query,
                                                       decoded, observed[n, index])
                labels[n, k].view(-1)[index] = observed_static(decoded, reference, observed[n, index])
        return labels
