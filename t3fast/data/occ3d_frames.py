"""Single label volumes of an Occ3D-layout dataset, for training the autoencoder."""

from __future__ import annotations

from pathlib import Path

import torch
from torch.utils.data import Dataset

from t3fast.data.occ3d import read_infos, read_labels
from t3fast.paths import inside


class Occ3DFrames(Dataset):
    """Every frame's ``semantics`` as ``uint8 [200, 200, 16]``; with ``flip`` each volume is
    mirrored in x and y with probability 0.5 each.

    Args:
        data_root: directory holding ``gts/<scene>/<token>/labels.npz``.
        info_path: the info pickle that lists the scenes' frames.
    """

    def __init__(self, data_root: str | Path, info_path: str | Path, flip: bool = False):
        self.root = Path(data_root)
        self.frames = [(scene, f["token"]) for scene, frames in read_infos(info_path).items() for f in frames]
        self.flip = flip

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> torch.Tensor:
        scene, token = self.frames[index]
        occ = torch.from_numpy(read_labels(inside(self.root / "gts", scene, token, "labels.npz"))["semantics"])
        if self.flip:
            for dim in (0, 1):
                if torch.rand(()).item() < 0.5:
                    occ = occ.flip(dim)
        return occ
