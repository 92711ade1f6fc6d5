"""Encoded triplanes of every frame of a set of synthetic scenes, kept on disk.

Stage 2 freezes the encoder, so each frame's triplane never changes: encoding the 11 frames
of every training window at every step would cost more than the forecaster itself on a CPU.
The planes are computed once per (encoder weights, scenes) and stored in float16 under a key
that hashes the encoder's weights, so runs that share a stage-1 checkpoint share the file.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from t3fast.data.synthetic.dataset import SyntheticScenes
from t3fast.io.checkpoint import load_checkpoint, save_checkpoint
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.triplane import Triplane


def encoder_digest(encoder: TriplaneEncoder) -> str:
    """Short hash of the encoder's weights."""
    h = hashlib.sha256()
    for name, tensor in sorted(encoder.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


@torch.no_grad()
def encode_scenes(
    encoder: TriplaneEncoder, scenes: SyntheticScenes, batch_size: int = 8, progress: bool = True
) -> list[Triplane]:
    """Per scene, planes ``[F, C, H, W]`` (float16, CPU) of its ``F`` frames."""
    encoder.eval()
    device = next(encoder.parameters()).device
    out = []
    for index in tqdm(range(len(scenes)), desc=f"encode {scenes.split} scenes", unit="scene", disable=not progress):
        packed = scenes.packed(index)
        chunks = []
        for start in range(0, packed.num_frames, batch_size):
            frames = [packed.frame_occ(t) for t in range(start, min(start + batch_size, packed.num_frames))]
            labels = torch.from_numpy(np.stack(frames)).to(device)
            chunks.append(encoder(labels).map(lambda p: p.half().cpu()))
        out.append(Triplane(*(None if chunks[0][i] is None else torch.cat([c[i] for c in chunks]) for i in range(3))))
    return out


def cached_scene_triplanes(
    encoder: TriplaneEncoder, scenes: SyntheticScenes, cache_dir: str | Path, progress: bool = True
) -> list[Triplane]:
    """:func:`encode_scenes`, read from ``cache_dir`` when this encoder already encoded these scenes."""
    key = f"{encoder_digest(encoder)}-{scenes.split}-{len(scenes)}x{scenes.frames_per_scene}"
    path = Path(cache_dir) / f"triplanes-{key}.pt"
    if path.exists():
        stored = load_checkpoint(path)
        return [Triplane(*planes) for planes in stored["planes"]]
    planes = encode_scenes(encoder, scenes, progress=progress)
    save_checkpoint({"planes": [tuple(p) for p in planes]}, path)
    return planes
