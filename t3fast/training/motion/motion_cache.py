"""What the motion head reads and learns from, for many windows, kept on disk.

The motion head of the flow forecaster (:mod:`t3fast.models.motion_head`) reads the agents'
velocities measured by the tracker in the last three past frames, the present xy plane and the
previous one (moved into the present ego frame); it learns from the agents' boxes. The planes
are the route planner's (:class:`~t3fast.training.planner.plan_cache.PlanCache`: two encodings
a window, shared with ``train-planner``); this cache adds per scene the velocities, measured as
at inference (:meth:`T3Former.agent_velocity`), and each agent's true motion over the cells the
render moves it by (:class:`~t3fast.training.world_model.motion_loss.AgentTargets`, made once
from the boxes: a batch's targets cost more than the head's step). Both come from labels only,
so the folder's name hashes the split's first scene and the plane's size, not the encoder.
One entry file per scene (:class:`~t3fast.training.cache_files.SceneFiles`: checked when read,
agent ids in range included, built again when broken, written atomically), so building is
resumable and shows progress.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from torch.nn import functional as F

from t3fast.data.sample import NUM_FUTURE, PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.forecast.agents import measured_velocities
from t3fast.host_syncs import reads_host
from t3fast.models.ego_motion import planar_poses
from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.world_model import T3Former
from t3fast.training.cache_files import Field, Layout, Payload, SceneFiles, world_digest
from t3fast.training.gathered import GatheredBatches
from t3fast.training.planner.plan_cache import PlanCache
from t3fast.training.world_model.motion_loss import AgentTargets, agent_targets
from t3fast.training.world_model.motion_targets import agent_motion

MOTION_CACHE_FORMAT = 3  # 2: per-agent targets instead of boxes; 3: checked entry files


@dataclass
class MotionWindows:
    """Motion-head inputs and targets: ``present``, ``previous`` xy planes ``[B, C, H, W]``,
    the tracker's ``velocity`` ``[B, 4, H, W]`` (plane cells per step) and the agents' true
    motion ``targets`` (:class:`~t3fast.training.world_model.motion_loss.AgentTargets`, A
    agents)."""

    present: Tensor
    previous: Tensor
    velocity: Tensor
    targets: AgentTargets

    def to(self, device: torch.device | str) -> MotionWindows:
        return self.map(lambda t: t.to(device))

    def select(self, index: slice | Tensor) -> MotionWindows:
        return self.map(lambda t: t[index])

    def map(self, fn) -> MotionWindows:
        t = self.targets
        return MotionWindows(fn(self.present), fn(self.previous), fn(self.velocity),
                             AgentTargets(fn(t.cells), fn(t.visible), fn(t.motion)))

    def __len__(self) -> int:
        return self.present.shape[0]


def _pad_agents(x: Tensor, agents: int) -> Tensor:
    """Per-agent targets ``[W, S, A, *]`` padded with agents that are never visible to ``agents``."""
    return F.pad(x, [0, 0] * (x.dim() - 3) + [0, agents - x.shape[2]])


class MotionCache(SceneFiles):
    """The windows of a :class:`SyntheticDriving` split as the motion head reads them.

    Args:
        windows: the windows (``flip=False``; mirroring happens per batch).
        model: an ego-aligned :class:`T3Former` with a tracker-prior flow forecaster.
        cache_dir: parent folder of this cache (``motion-<world>-<split>-...``) and of the
            planes' :class:`~t3fast.training.planner.plan_cache.PlanCache`.
    """

    kind = "motion"
    desc = "measure agent motion"

    def __init__(self, windows: SyntheticDriving, model: T3Former, cache_dir: str | Path):
        if not isinstance(model.forecaster, FlowTriplaneForecaster):
            raise ValueError("the motion head corrects the tracker: the model needs a flow forecaster")
        self.model = model
        self.planes = PlanCache(windows, model, cache_dir)
        h, w = model.encoder.config.plane_shape[:2]
        scenes = windows.scenes
        key = (f"{world_digest(scenes)}-{scenes.split}-{scenes.frames_per_scene}f-stride{windows.stride}-{h}x{w}"
               f"-v{MOTION_CACHE_FORMAT}")
        super().__init__(windows, Path(cache_dir) / f"motion-{key}", key)
        self._plane = (h, w)
        self._data: dict[str, Tensor] | None = None

    def layout(self, scene: int) -> Layout:
        windows = self.windows_of(scene)
        return {"velocity": Field(torch.float32, (windows, 4, *self._plane)),
                "cells": Field(torch.int16, (windows, *self._plane)),
                "visible": Field(torch.bool, (windows, NUM_FUTURE, "agents")),
                "motion": Field(torch.float32, (windows, NUM_FUTURE, "agents", 2))}

    def check(self, payload: Payload) -> str | None:
        """Every cell belongs to one of the scene's agents or to none (-1)."""
        cells, agents = payload["cells"], payload["motion"].shape[2]
        if cells.numel() and not (-1 <= int(cells.min()) and int(cells.max()) < agents):
            return f"agent ids {int(cells.min())}..{int(cells.max())} outside -1..{agents - 1}"
        return None

    @torch.no_grad()
    def build(self, progress: bool = True) -> int:
        """Cache every scene missing or broken, and the planes; returns how many scenes were cached here."""
        self.planes.build(progress)
        return super().build(progress)

    def build_scene(self, scene: int) -> Payload:
        samples = self.scene_windows(scene)
        velocity = torch.cat([self._velocity(s) for s in samples]).cpu()  # [W, 4, H, W]
        return scene_targets([s.boxes for s in samples], [s.box_valid for s in samples], velocity)

    def _velocity(self, sample) -> Tensor:
        """The tracker's velocities ``[1, 4, H, W]`` of a window, exactly as at inference."""
        device = next(self.model.parameters()).device
        recent = slice(PRESENT - 2, PRESENT + 1)
        poses = planar_poses(sample.ego_poses[None], PRESENT)[:, recent].to(device)
        return measured_velocities(sample.occ[None, recent].to(device), poses, self._plane)

    def batches(self, device: torch.device | str = "cpu") -> MotionBatches:
        """The windows gathered a batch at a time, on ``device`` where they fit; the per-agent
        fields padded to the split's most agents."""
        if self._data is None:
            parts = self.read_scenes()
            agents = max(p["motion"].shape[2] for p in parts)
            self._data = {
                "velocity": torch.cat([p["velocity"] for p in parts]),
                "cells": torch.cat([p["cells"] for p in parts]),
                "visible": torch.cat([_pad_agents(p["visible"], agents) for p in parts]),
                "motion": torch.cat([_pad_agents(p["motion"], agents) for p in parts]),
            }
        return MotionBatches({"xy": self.planes.data()["xy"], **self._data}, device)

    def all(self) -> MotionWindows:
        """Every window at once."""
        return self.batches().all()


class MotionBatches(GatheredBatches):
    """A :class:`MotionCache`'s windows as the motion head reads them (:class:`MotionWindows`,
    planes back to float32). Where the host may read (:func:`~t3fast.host_syncs.reads_host`:
    training on the CPU) a batch keeps only the agents its cells name; elsewhere every padded
    agent (never visible), so the batch's shapes do not depend on its data."""

    def batch(self, rows: dict[str, Tensor]) -> MotionWindows:
        xy, cells = rows["xy"].float(), rows["cells"].long()
        visible, motion = rows["visible"], rows["motion"]
        if reads_host(self.target):
            agents = max(int(cells.max()) + 1, 1)
            visible, motion = visible[:, :, :agents], motion[:, :, :agents]
        return MotionWindows(xy[:, 1], xy[:, 0], rows["velocity"], AgentTargets(cells, visible, motion))


def scene_targets(boxes: list[Tensor], box_valid: list[Tensor], velocity: Tensor) -> dict[str, Tensor]:
    """What a scene's file holds: the windows' velocities ``[W, 4, H, W]`` and their agents'
    :class:`AgentTargets` (``cells`` as int16) from each window's ``boxes`` ``[11, A, 7]`` (present
    frame) and ``box_valid`` ``[11, A]``."""
    agents = max(b.shape[1] for b in boxes)
    valid = torch.stack([F.pad(v, [0, agents - v.shape[1]]) for v in box_valid])
    boxes = torch.stack([F.pad(b, [0, 0, 0, agents - b.shape[1]]) for b in boxes])
    target, moving, static, _, covered, owner = agent_motion(boxes, valid, tuple(velocity.shape[-2:]))
    t = agent_targets(target, moving, static, covered, owner, velocity, agents)
    return {"velocity": velocity, "cells": t.cells.short(), "visible": _pad_agents(t.visible, agents),
            "motion": _pad_agents(t.motion, agents)}


