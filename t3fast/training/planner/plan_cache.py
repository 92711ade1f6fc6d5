"""What the route planner reads, for many windows, kept on disk: the planner trained on its own.

The route planner (:class:`~t3fast.models.route_planner.RoutePlanner`) reads only the present
xy plane, the previous frame's (moved into the present ego frame) and the past displacements:
two encodings per window instead of the eleven of the forecaster's cache
(:mod:`t3fast.training.world_model.latent_cache`), so it can learn from many more scenes at the
same cost. The frames are encoded as at inference (:meth:`~t3fast.forecast.encode.EncodePast.planes`). One
entry file per scene (float16 planes, about 0.3 MB a window with the small autoencoder;
:class:`~t3fast.training.cache_files.SceneFiles`: checked when read, built again when broken,
written atomically), so building is resumable and shows progress. The folder's name hashes the
encoder's weights and the split's first scene, so a new autoencoder or a changed world builds a
new cache. A planner that does not read the scene (``planes=False``) needs no encoding at all:
its cache holds the displacements only (and empty planes)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from t3fast.data.route import route_command
from t3fast.data.sample import NUM_FUTURE, NUM_PAST, PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.models.ego_motion import planar_poses
from t3fast.models.world_model import T3Former
from t3fast.training.cache_files import Field, Layout, Payload, SceneFiles, world_digest
from t3fast.training.gathered import GatheredBatches
from t3fast.training.triplane_cache import encoder_digest

PLAN_CACHE_FORMAT = 3  # 2: checked entry files; 3: the encoder's stem as label_conv3d (planes moved by up to 0.04)
ENCODE_WINDOWS = 8  # windows (two frames each) per encoder call


@dataclass
class PlanWindows:
    """Planner inputs and targets: ``present``, ``previous`` xy planes ``[B, C, H, W]`` (the
    previous frame in the present ego frame), ``past_actions`` ``[B, 4, 2]``, the true
    ``future_actions`` ``[B, 6, 2]`` and the route ``command`` ``[B]`` (int64; -1: none)."""

    present: Tensor
    previous: Tensor
    past_actions: Tensor
    future_actions: Tensor
    command: Tensor

    def to(self, device: torch.device | str) -> PlanWindows:
        return PlanWindows(*(t.to(device) for t in (self.present, self.previous, self.past_actions,
                                                      self.future_actions, self.command)))

    def inputs(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The planner's arguments (:meth:`RoutePlanner.forward`)."""
        return self.present, self.previous, self.past_actions, self.command


class PlanCache(SceneFiles):
    """The windows of a :class:`SyntheticDriving` split as the route planner reads them.

    Args:
        windows: the windows (``flip=False``; mirroring happens per batch).
        model: an ego-aligned :class:`T3Former` whose frozen encoder encodes the frames.
        cache_dir: parent folder; the cache is ``cache_dir/plan-<encoder>-<world>-<split>-...``.
        planes: encode the planes; False: the displacements only (the planes are empty,
            ``[B, 0, 1, 1]``), for a planner that does not read the scene.
    """

    kind = "plan"

    def __init__(self, windows: SyntheticDriving, model: T3Former, cache_dir: str | Path, planes: bool = True):
        if windows.flip:
            raise ValueError("PlanCache stores windows as generated: pass flip=False")
        if not model.ego_aligned:
            raise ValueError("the route planner reads ego-aligned planes: the model needs ego_aligned=True")
        self.model, self.planes = model, planes
        scenes = windows.scenes
        source = encoder_digest(model.encoder) if planes else "motion"
        key = (f"{source}-{world_digest(scenes)}-{scenes.split}-{scenes.frames_per_scene}f"
               f"-stride{windows.stride}-v{PLAN_CACHE_FORMAT}")
        super().__init__(windows, Path(cache_dir) / f"plan-{key}", key)
        self.desc = "encode planner windows" if planes else "planner windows"
        c, (h, w) = model.encoder.config.channels, model.encoder.config.plane_shape[:2]
        self._plane_shape = (c, h, w) if planes else (0, 1, 1)
        self._data: dict[str, Tensor] | None = None

    def layout(self, scene: int) -> Layout:
        windows = self.windows_of(scene)
        return {"xy": Field(torch.float16, (windows, 2, *self._plane_shape)),
                "past_actions": Field(torch.float32, (windows, NUM_PAST, 2)),
                "future_actions": Field(torch.float32, (windows, NUM_FUTURE, 2))}

    def build_scene(self, scene: int) -> Payload:
        samples = self.scene_windows(scene)
        device = next(self.model.parameters()).device
        xy = self._encode(samples, device) if self.planes else torch.zeros(len(samples), 2, 0, 1, 1)
        return {
            "xy": xy.half().cpu(),  # [W, 2 (previous, present), C, H, W]
            "past_actions": torch.stack([s.past_actions for s in samples]),
            "future_actions": torch.stack([s.future_actions for s in samples]),
        }

    def _encode(self, samples: list, device: torch.device) -> Tensor:
        """The previous and present xy planes ``[W, 2, C, H, W]`` of the windows ``samples``."""
        occ = torch.stack([s.occ[PRESENT - 1 : PRESENT + 1] for s in samples]).to(device)
        poses = torch.stack([planar_poses(s.ego_poses[None], PRESENT)[0, PRESENT - 1 : PRESENT + 1]
                             for s in samples]).to(device)
        encode = self.model.pipeline.encode
        return torch.cat([encode.planes(occ[i : i + ENCODE_WINDOWS], poses[i : i + ENCODE_WINDOWS]).xy
                          for i in range(0, len(samples), ENCODE_WINDOWS)])

    def data(self) -> dict[str, Tensor]:
        """Every window's fields, read once: ``xy`` float16 ``[N, 2, C, H, W]`` (previous,
        present), ``past_actions`` ``[N, 4, 2]``, ``future_actions`` ``[N, 6, 2]``."""
        if self._data is None:
            parts = self.read_scenes()
            self._data = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
        return self._data

    def batches(self, device: torch.device | str = "cpu") -> PlanBatches:
        """The windows gathered a batch at a time, on ``device`` where they fit."""
        data = self.data()
        return PlanBatches({**data, "command": route_command(data["future_actions"])}, device)

    def all(self) -> PlanWindows:
        """Every window at once, as the planner reads them."""
        return self.batches().all()


class PlanBatches(GatheredBatches):
    """A :class:`PlanCache`'s windows as the planner reads them (:class:`PlanWindows`, planes
    back to float32), with the route command derived from the future
    (:func:`~t3fast.data.route.route_command`)."""

    def batch(self, rows: dict[str, Tensor]) -> PlanWindows:
        xy = rows["xy"].float()
        return PlanWindows(xy[:, 1], xy[:, 0], rows["past_actions"], rows["future_actions"], rows["command"])
