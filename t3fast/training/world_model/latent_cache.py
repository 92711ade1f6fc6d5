"""Ego-aligned, encoded training windows kept on disk: stage 2 without an encoder in the step.

The encoder is frozen in stage 2, so a window's 11 frames moved into its present ego frame
(:func:`~t3fast.training.world_model.windows.ego_aligned_window`) always encode to the same
planes. Encoding them costs more than the forecaster's whole step on a CPU, so each window is
encoded once, stored in float16 (one file per window, about 2.3 MB with the small
autoencoder), and read by every later run and ablation. A window's file also holds what the
motion targets are made from (the agents' boxes and the ego's displacements) and the agents'
velocities measured in the last three past frames
(:func:`~t3fast.agents.tracker.tracker_velocities`, the tracker prior).

The cache folder's name hashes the encoder's weights and the data of the split's first scene,
so a new autoencoder or a changed world builds a new cache instead of reading stale planes;
:data:`CACHE_FORMAT` changes with what a window's file holds. Each file is an entry of
:mod:`t3fast.training.cache_files`: :meth:`AlignedLatentCache.build` checks every file (its
window, fields, shapes, finite values) and builds the missing and broken ones again, so
building is resumable and a rerun repairs a damaged cache; every file is written atomically.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor
from torch.utils.data import Dataset
from tqdm import tqdm

from t3fast.agents.tracker import tracker_velocities
from t3fast.data.classes import FREE, IGNORE
from t3fast.data.sample import NUM_FUTURE, NUM_PAST, PRESENT, WINDOW, DrivingSample
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import DataFormatError
from t3fast.host_syncs import reads_host
from t3fast.models.triplane import Triplane
from t3fast.models.world_model import T3Former
from t3fast.training.cache_files import (
    BrokenEntry,
    Field,
    Layout,
    Payload,
    read_entry,
    read_or_none,
    world_digest,
    write_entry,
)
from t3fast.training.gathered import GatheredBatches
from t3fast.training.triplane_cache import encoder_digest, plane_fields, planes_from, planes_payload
from t3fast.training.world_model.windows import SequenceBatch, ego_aligned_window

# 2: the agents' velocities are stored with each window; 3: over one and two steps; 4: chained; 5: checked entries;
# 6: the encoder's stem as label_conv3d (planes moved by up to 0.04)
CACHE_FORMAT = 6


@dataclass
class AlignedWindow:
    """One cached window: planes ``[11, C, H, W]`` (float32 once read) of its frames in the
    present ego frame; ``boxes`` ``[11, A, 7]`` and ``box_valid`` ``[11, A]`` in the present
    frame; ``past_actions`` ``[4, 2]``, ``future_actions`` ``[6, 2]``; the agents' ``velocity``
    ``[4, H, W]`` (plane cells per step)."""

    planes: Triplane
    boxes: Tensor
    box_valid: Tensor
    past_actions: Tensor
    future_actions: Tensor
    velocity: Tensor


class AlignedLatentCache(Dataset):
    """The windows of a :class:`SyntheticDriving` split, ego-aligned and encoded, on disk.

    Args:
        windows: the training windows (``flip=False``: the cache stores them as generated;
            augmentation happens after reading).
        model: an ego-aligned :class:`T3Former` whose frozen encoder encodes the frames.
        cache_dir: parent folder; the cache is ``cache_dir/aligned-<encoder>-<world>-<split>``.
    """

    def __init__(self, windows: SyntheticDriving, model: T3Former, cache_dir: str | Path):
        if windows.flip:
            raise ValueError("AlignedLatentCache stores windows as generated: pass flip=False")
        self.windows, self.model = windows, model
        split = windows.scenes.split
        self.key = (f"{encoder_digest(model.encoder)}-{world_digest(windows.scenes)}-{split}"
                    f"-{windows.scenes.frames_per_scene}f-v{CACHE_FORMAT}")
        self.root = Path(cache_dir) / f"aligned-{self.key}"
        h, w = model.encoder.config.plane_shape[:2]
        self._layout: Layout = {
            **plane_fields(model.encoder.config, WINDOW),
            "boxes": Field(torch.float32, (WINDOW, "agents", 7)),
            "box_valid": Field(torch.bool, (WINDOW, "agents")),
            "past_actions": Field(torch.float32, (NUM_PAST, 2)),
            "future_actions": Field(torch.float32, (NUM_FUTURE, 2)),
            "velocity": Field(torch.float32, (4, h, w)),
        }

    def path(self, index: int) -> Path:
        scene, start = self.windows.locate(index)
        return self.root / f"scene{scene:05d}-start{start:03d}.pt"

    def identity(self, index: int) -> dict:
        scene, start = self.windows.locate(index)
        return {"cache": "aligned", "key": self.key, "split": self.windows.scenes.split, "scene": scene,
                "start": start}

    def missing(self) -> list[int]:
        """Indices of the windows not in the cache, or whose file is broken (each named in a
        warning); reads every file."""
        return [i for i in range(len(self.windows))
                if read_or_none(self.path(i), self.identity(i), self._layout) is None]

    @torch.no_grad()
    def build(self, progress: bool = True) -> int:
        """Encode every window that is missing or broken; returns how many were encoded."""
        todo = self.missing()
        for index in tqdm(todo, desc="encode aligned windows", unit="window", disable=not progress or not todo):
            write_entry(self.path(index), self.identity(index), self._encode(index))
        return len(todo)

    def _encode(self, index: int) -> Payload:
        device = next(self.model.parameters()).device
        sample = self.windows[index]
        occ, poses = sample.occ[None].to(device), sample.ego_poses[None].to(device)
        planes, moved = ego_aligned_window(self.model, occ, poses)
        recent = moved[:, PRESENT - 2 : PRESENT + 1]
        recent = recent.masked_fill(recent == IGNORE, FREE)  # what a past frame did not see is free
        velocity = tracker_velocities(recent, tuple(planes.xy.shape[-2:]))[0]
        return {
            **planes_payload(planes.map(lambda p: p[0].half().cpu())),
            "boxes": sample.boxes,
            "box_valid": sample.box_valid,
            "past_actions": sample.past_actions,
            "future_actions": sample.future_actions,
            "velocity": velocity.cpu(),
        }

    def __len__(self) -> int:
        return len(self.windows)

    def entry(self, index: int) -> Payload:
        """Window ``index`` as stored (planes in float16)."""
        path = self.path(index)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: window {index} is not cached yet (build() first)")
        try:
            return read_entry(path, self.identity(index), self._layout)
        except BrokenEntry as exc:  # broken since build() checked it: the next build() encodes it again
            raise DataFormatError(f"{path}: {exc}; run again to encode it anew") from exc

    def __getitem__(self, index: int) -> AlignedWindow:
        state = self.entry(index)
        planes = planes_from(state).map(lambda p: p.float())
        return AlignedWindow(planes, state["boxes"], state["box_valid"], state["past_actions"], state["future_actions"],
                             state["velocity"])

    def stored_bytes(self) -> int:
        """About what holding every window as stored takes: the size of its files."""
        return sum(self.path(i).stat().st_size for i in range(len(self)))


class AlignedBatches(GatheredBatches):
    """An :class:`AlignedLatentCache`'s windows held whole, each batch an :class:`AlignedBatch`
    gathered where they are (on a GPU where they fit), nothing read from disk in the step. Each
    window's boxes are padded with invalid ones to the split's most agents, so a batch's shapes
    do not depend on its windows (one CUDA graph serves them all); where the host may read
    (:func:`~t3fast.host_syncs.reads_host`: on the CPU) a batch keeps the most agents of its
    windows, as :func:`collate_aligned` pads them.

    Args:
        cache: a built cache.
        device: the training device (the windows are held there where they fit).
    """

    def __init__(self, cache: AlignedLatentCache, device: torch.device | str = "cpu", progress: bool = True):
        entries = [cache.entry(i) for i in tqdm(range(len(cache)), desc="hold aligned windows", unit="window",
                                                 disable=not progress)]
        agents = max(e["boxes"].shape[1] for e in entries)
        padded = ("boxes", "box_valid")
        fields = {name: torch.stack([e[name] for e in entries]) for name in entries[0] if name not in padded}
        fields.update({name: torch.stack([_pad_agents(e[name], agents) for e in entries]) for name in padded})
        fields["agents"] = torch.tensor([e["boxes"].shape[1] for e in entries])
        super().__init__(fields, device)

    def batch(self, rows: dict[str, Tensor]) -> AlignedBatch:
        boxes, valid = rows["boxes"], rows["box_valid"]
        if reads_host(self.target):
            agents = int(rows["agents"].max())
            boxes, valid = boxes[:, :, :agents], valid[:, :, :agents]
        planes = Triplane(*(rows[name].float() if name in rows else None for name in Triplane._fields))
        return AlignedBatch(planes, boxes, valid, rows["past_actions"], rows["future_actions"], rows["velocity"])


class LabelledAlignedWindows(Dataset):
    """The windows of a built :class:`AlignedLatentCache` with their labels and poses, for the
    labels path of stage 2 (:func:`~t3fast.training.world_model.windows.collate_windows`):
    ``(DrivingSample, planes [11, C, H, W])`` pairs, the planes :func:`ego_aligned_window`
    gives those labels (stored in float16)."""

    def __init__(self, cache: AlignedLatentCache):
        self.cache = cache

    def __len__(self) -> int:
        return len(self.cache)

    def __getitem__(self, index: int) -> tuple[DrivingSample, Triplane]:
        return self.cache.windows[index], self.cache[index].planes


class ResidentAlignedWindows(Dataset):
    """:class:`LabelledAlignedWindows` held in ``device`` memory (a GPU's, where they fit:
    :func:`~t3fast.training.gathered.fits_on`): each scene's frames and poses once, each
    window's planes in float16 and actions; a batch is gathered on the device, already collated
    (``__getitems__``), so the step reads nothing from disk or the host."""

    def __init__(self, labelled: LabelledAlignedWindows, device: torch.device, progress: bool = True):
        windows = labelled.cache.windows
        self.device = device  # where the batches are made (the trainer's loader reads it)
        scenes, frames = len(windows.scenes), windows.scenes.frames_per_scene
        first = windows[0]
        self.occ = torch.empty(scenes, frames, *first.occ.shape[1:], dtype=first.occ.dtype, device=device)
        self.poses = torch.empty(scenes, frames, 4, 4, dtype=first.ego_poses.dtype, device=device)
        # per window: its scene and first frame [N, 2]
        self.located = torch.tensor([windows.locate(i) for i in range(len(windows))], device=device)
        items = []
        for i in tqdm(range(len(windows)), desc="windows to the device", unit="window", disable=not progress):
            sample, planes = windows[i], labelled.cache[i].planes
            scene, start = windows.locate(i)
            self.occ[scene, start : start + WINDOW] = sample.occ.to(device)
            self.poses[scene, start : start + WINDOW] = sample.ego_poses.to(device)
            half = planes.map(lambda p: p.to(device, torch.float16))
            items.append((half, sample.past_actions, sample.future_actions))
        self.planes = Triplane(*(None if items[0][0][k] is None else torch.stack([it[0][k] for it in items])
                                 for k in range(3)))
        self.past_actions = torch.stack([it[1] for it in items]).to(device)
        self.future_actions = torch.stack([it[2] for it in items]).to(device)

    def __len__(self) -> int:
        return self.located.shape[0]

    def __getitems__(self, indices: list[int]) -> SequenceBatch:
        index = torch.as_tensor(indices, device=self.located.device)
        scene, start = self.located[index].unbind(1)
        frames = start[:, None] + torch.arange(WINDOW, device=start.device)
        return SequenceBatch(occ=self.occ[scene[:, None], frames], planes=self.planes.map(lambda p: p[index].float()),
                             past_actions=self.past_actions[index], future_actions=self.future_actions[index],
                             ego_poses=self.poses[scene[:, None], frames])


def resident_bytes(labelled: LabelledAlignedWindows) -> int:
    """The memory :class:`ResidentAlignedWindows` takes for ``labelled``."""
    windows, cache = labelled.cache.windows, labelled.cache
    first, planes = windows[0], cache[0].planes
    frames = len(windows.scenes) * windows.scenes.frames_per_scene
    per_frame = first.occ[0].numel() * first.occ.element_size() + 16 * first.ego_poses.element_size()
    per_window = 2 * sum(p.numel() for p in planes if p is not None) + 20 * first.past_actions.element_size()
    return frames * per_frame + len(windows) * per_window


@dataclass
class AlignedBatch:
    """Cached windows collated: planes ``[B, 11, C, H, W]``, ``boxes`` ``[B, 11, A, 7]`` (A
    padded with invalid boxes), ``box_valid`` ``[B, 11, A]``, actions ``[B, 4, 2]``,
    ``[B, 6, 2]``, ``velocity`` ``[B, 4, H, W]``."""

    planes: Triplane
    boxes: Tensor
    box_valid: Tensor
    past_actions: Tensor
    future_actions: Tensor
    velocity: Tensor

    def to(self, device: torch.device | str) -> AlignedBatch:
        return AlignedBatch(self.planes.map(lambda p: p.to(device)), self.boxes.to(device), self.box_valid.to(device),
                            self.past_actions.to(device), self.future_actions.to(device), self.velocity.to(device))


def _pad_agents(x: Tensor, agents: int) -> Tensor:
    """A window's boxes ``[11, A, 7]`` or their validity ``[11, A]`` padded to ``agents`` with
    invalid (zero) boxes."""
    return torch.nn.functional.pad(x, (0, 0) * (x.dim() - 2) + (0, agents - x.shape[1]))


def collate_aligned(items: list[AlignedWindow]) -> AlignedBatch:
    """Stack cached windows; windows with fewer agents get invalid padding boxes."""
    agents = max(item.boxes.shape[1] for item in items)
    first = items[0].planes
    planes = Triplane(*(None if first[i] is None else torch.stack([it.planes[i] for it in items]) for i in range(3)))
    return AlignedBatch(
        planes,
        torch.stack([_pad_agents(it.boxes, agents) for it in items]),
        torch.stack([_pad_agents(it.box_valid, agents) for it in items]),
        torch.stack([it.past_actions for it in items]),
        torch.stack([it.future_actions for it in items]),
        torch.stack([it.velocity for it in items]),
    )
