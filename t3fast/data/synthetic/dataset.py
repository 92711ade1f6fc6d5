"""Torch datasets over synthetic scenes: 11-frame samples and single frames.

Splits use disjoint seed ranges: scene ``k`` of split ``s`` has seed
``SPLIT_SEEDS[s] + k``. Generated scenes are cached in memory, compressed
(about 2-3 MB per 40-frame scene instead of 50 MB), so that reading the same
scene again costs a decompression (~1 ms per frame) instead of a regeneration.
"""

from __future__ import annotations

import threading
import zlib
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset

from t3fast.data import classes as C
from t3fast.data.sample import WINDOW, DrivingSample, build_sample, random_flip, window_starts
from t3fast.data.synthetic.scene import SyntheticScene, generate_scene, world_to_ego

SPLIT_SEEDS = {"train": 0, "val": 1_000_000, "test": 2_000_000}
SPLIT_SIZE = 1_000_000  # seeds per split: num_scenes may not exceed it
DEFAULT_NUM_SCENES = {"train": 200, "val": 40, "test": 40}
#: a scene is generated whole in memory (about 1.7 GB and 45 s for 1000 frames)
MAX_FRAMES_PER_SCENE = 1000


def scene_seed(split: str, index: int) -> int:
    """Seed of scene ``index`` of ``split``."""
    if split not in SPLIT_SEEDS:
        raise ValueError(f"unknown split {split!r}; expected one of {sorted(SPLIT_SEEDS)}")
    if not 0 <= index < SPLIT_SIZE:
        raise ValueError(f"scene index {index} outside [0, {SPLIT_SIZE})")
    return SPLIT_SEEDS[split] + index


def scene_name(split: str, index: int) -> str:
    return f"synthetic-{split}-{index:05d}"


@dataclass
class PackedScene:
    """A scene kept compressed: per-frame zlib'd labels and bit-packed masks, plus the
    small arrays. ``boxes`` ``[T, N, 7]`` are in each frame's own ego frame; ``valid``
    ``[T, N]`` marks agents whose centre is inside that frame's grid."""

    name: str
    occ: list[bytes]
    mask: list[bytes]
    ego_poses: np.ndarray
    boxes: np.ndarray
    valid: np.ndarray
    labels: np.ndarray

    @classmethod
    def pack(cls, name: str, scene: SyntheticScene) -> PackedScene:
        boxes = np.stack([world_to_ego(scene.boxes_world[t], scene.ego_poses[t]) for t in range(len(scene.occ))])
        half = C.GRID_UPPER[0]
        valid = (np.abs(boxes[..., 0]) < half) & (np.abs(boxes[..., 1]) < half)
        return cls(
            name=name,
            occ=[zlib.compress(f.tobytes(), 1) for f in scene.occ],
            mask=[zlib.compress(np.packbits(m).tobytes(), 1) for m in scene.mask_camera],
            ego_poses=scene.ego_poses,
            boxes=boxes,
            valid=valid,
            labels=scene.labels,
        )

    @property
    def num_frames(self) -> int:
        return len(self.occ)

    def frame_occ(self, t: int) -> np.ndarray:
        return np.frombuffer(zlib.decompress(self.occ[t]), dtype=np.uint8).reshape(C.GRID_SHAPE)

    def frame_mask(self, t: int) -> np.ndarray:
        bits = np.frombuffer(zlib.decompress(self.mask[t]), dtype=np.uint8)
        return np.unpackbits(bits, count=int(np.prod(C.GRID_SHAPE))).astype(bool).reshape(C.GRID_SHAPE)

    def window(self, start: int) -> DrivingSample:
        """The 11-frame sample that begins at frame ``start``."""
        frames = range(start, start + WINDOW)
        return build_sample(
            occ=np.stack([self.frame_occ(t) for t in frames]),
            mask_camera=np.stack([self.frame_mask(t) for t in frames]),
            ego_poses=self.ego_poses[start : start + WINDOW],
            boxes=self.boxes[start : start + WINDOW],
            box_valid=self.valid[start : start + WINDOW],
            box_labels=self.labels,
            scene=self.name,
            start=start,
        )


class SyntheticScenes:
    """The scenes of one split, generated on first use and cached compressed."""

    def __init__(self, split: str = "train", num_scenes: int | None = None, frames_per_scene: int = 40):
        self.split = split
        self.num_scenes = DEFAULT_NUM_SCENES[split] if num_scenes is None else num_scenes
        scene_seed(split, max(self.num_scenes - 1, 0))  # validates split and size
        if not WINDOW <= frames_per_scene <= MAX_FRAMES_PER_SCENE:
            raise ValueError(
                f"frames_per_scene must be {WINDOW}..{MAX_FRAMES_PER_SCENE} (a scene is generated whole in memory), "
                f"got {frames_per_scene}"
            )
        self.frames_per_scene = frames_per_scene
        self._cache: dict[int, PackedScene] = {}
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self.num_scenes

    def name(self, index: int) -> str:
        return scene_name(self.split, index)

    def generate(self, index: int) -> SyntheticScene:
        """Generate scene ``index`` (uncached, full arrays)."""
        if not 0 <= index < self.num_scenes:
            raise IndexError(f"scene {index} out of range for {self.num_scenes} scenes")
        return generate_scene(scene_seed(self.split, index), self.frames_per_scene)

    def packed(self, index: int) -> PackedScene:
        """Scene ``index``, from the cache or generated now."""
        scene = self._cache.get(index)
        if scene is None:
            scene = PackedScene.pack(self.name(index), self.generate(index))
            with self._lock:
                self._cache[index] = scene
        return scene


class SyntheticDriving(Dataset):
    """11-frame ``DrivingSample``s from sliding windows over synthetic scenes.

    Args:
        split: ``"train"``, ``"val"`` or ``"test"`` (disjoint seed ranges).
        num_scenes: scenes in the split (defaults: 200 / 40 / 40).
        frames_per_scene: 2 Hz frames per scene (40 = 20 s, like nuScenes).
        stride: frames between the starts of consecutive windows.
        flip: apply ``random_flip`` (x and y, each with probability 0.5).
    """

    def __init__(
        self,
        split: str = "train",
        num_scenes: int | None = None,
        frames_per_scene: int = 40,
        stride: int = 1,
        flip: bool = False,
    ):
        self.scenes = SyntheticScenes(split, num_scenes, frames_per_scene)
        self.starts = window_starts(frames_per_scene, stride)
        self.stride, self.flip = stride, flip

    def __len__(self) -> int:
        return len(self.scenes) * len(self.starts)

    def locate(self, index: int) -> tuple[int, int]:
        """(scene index, first frame) of window ``index``."""
        if not 0 <= index < len(self):
            raise IndexError(index)
        scene, k = divmod(index, len(self.starts))
        return scene, self.starts[k]

    def __getitem__(self, index: int) -> DrivingSample:
        scene, start = self.locate(index)
        sample = self.scenes.packed(scene).window(start)
        return random_flip(sample) if self.flip else sample


class SyntheticFrames(Dataset):
    """Single label volumes ``uint8 [200, 200, 16]`` (every frame of every scene), e.g. for
    training the triplane autoencoder. With ``flip`` each volume is mirrored in x and y
    with probability 0.5 each."""

    def __init__(
        self, split: str = "train", num_scenes: int | None = None, frames_per_scene: int = 40, flip: bool = False
    ):
        self.scenes = SyntheticScenes(split, num_scenes, frames_per_scene)
        self.flip = flip

    def __len__(self) -> int:
        return len(self.scenes) * self.scenes.frames_per_scene

    def __getitem__(self, index: int) -> torch.Tensor:
        if not 0 <= index < len(self):
            raise IndexError(index)
        scene, t = divmod(index, self.scenes.frames_per_scene)
        occ = torch.from_numpy(self.scenes.packed(scene).frame_occ(t).copy())
        if self.flip:
            for dim in (0, 1):
                if torch.rand(()).item() < 0.5:
                    occ = occ.flip(dim)
        return occ
