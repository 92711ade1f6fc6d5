"""Where stage 1's single frames come from."""

from __future__ import annotations

from torch.utils.data import Dataset

from t3fast.data.synthetic import SyntheticFrames
from t3fast.training.configs import FramesConfig


def frames_dataset(data: FramesConfig, split: str) -> Dataset:
    """Single ``uint8 [200, 200, 16]`` frames of a split."""
    if data.source == "synthetic":
        scenes = data.train_scenes if split == "train" else data.val_scenes
        return SyntheticFrames(split, scenes, data.frames_per_scene, flip=data.flip and split == "train")
    if data.source == "occ3d":
        from t3fast.data.occ3d_frames import Occ3DFrames

        info = data.occ3d_train_info if split == "train" else data.occ3d_val_info
        return Occ3DFrames(data.occ3d_root, info, flip=data.flip and split == "train")
    raise ValueError(f"data.source must be 'synthetic' or 'occ3d', got {data.source!r}")
