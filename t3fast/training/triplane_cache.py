"""Encoded triplanes of every frame of a set of synthetic scenes, kept on disk.

Stage 2 freezes the encoder, so each frame's triplane never changes: encoding the 11 frames
of every training window at every step would cost more than the forecaster itself on a CPU.
The planes are computed once per (encoder weights, scenes) and stored in float16, one entry
file per scene (:mod:`t3fast.training.cache_files`: checked when read, built again when
broken, written atomically, so building is resumable) in a folder whose name hashes the
encoder's weights and the data of the split's first scene, so runs that share a stage-1
checkpoint share the files.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from t3fast.data.synthetic.dataset import PackedScene, SyntheticScenes
from t3fast.models.config import AutoencoderConfig
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.triplane import Triplane
from t3fast.training.cache_files import Dim, Field, Layout, read_or_none, world_digest, write_entry

# 2: one checked entry file per scene; 3: the encoder's stem as label_conv3d (planes moved by up to 0.04)
TRIPLANE_CACHE_FORMAT = 3


def encoder_digest(encoder: TriplaneEncoder) -> str:
    """Short hash of the encoder's weights."""
    h = hashlib.sha256()
    for name, tensor in sorted(encoder.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


def plane_fields(config: AutoencoderConfig, *leading: Dim) -> Layout:
    """The cache fields (float16) of the planes ``config``'s encoder makes, each with the
    ``leading`` axes: ``xy`` ``[*leading, C, X', Y']``, and ``xz``, ``yz`` unless the latent is BEV."""
    x, y, z = config.plane_shape
    sizes = {"xy": (x, y)} if config.latent == "bev" else {"xy": (x, y), "xz": (x, z), "yz": (y, z)}
    return {name: Field(torch.float16, (*leading, config.channels, *hw)) for name, hw in sizes.items()}


def planes_payload(planes: Triplane) -> dict[str, torch.Tensor]:
    """The planes that are there, by name (a BEV latent has no ``xz``, ``yz``)."""
    return {name: p for name, p in zip(Triplane._fields, planes) if p is not None}


def planes_from(payload: dict[str, torch.Tensor]) -> Triplane:
    """:func:`planes_payload` read back (float16)."""
    return Triplane(*(payload.get(name) for name in Triplane._fields))


@torch.no_grad()
def encode_scene(encoder: TriplaneEncoder, scene: PackedScene, batch_size: int = 8) -> Triplane:
    """Planes ``[F, C, H, W]`` (float16, CPU) of the scene's ``F`` frames."""
    encoder.eval()
    device = next(encoder.parameters()).device
    chunks = []
    for start in range(0, scene.num_frames, batch_size):
        frames = [scene.frame_occ(t) for t in range(start, min(start + batch_size, scene.num_frames))]
        labels = torch.from_numpy(np.stack(frames)).to(device)
        chunks.append(encoder(labels).map(lambda p: p.half().cpu()))
    return Triplane.cat(chunks)


def cached_scene_triplanes(
    encoder: TriplaneEncoder, scenes: SyntheticScenes, cache_dir: str | Path, progress: bool = True
) -> list[Triplane]:
    """Per scene, planes ``[F, C, H, W]`` (float16, CPU) of its ``F`` frames, read from
    ``cache_dir`` where this encoder already encoded the scene, else encoded and stored there."""
    key = (f"{encoder_digest(encoder)}-{world_digest(scenes)}-{scenes.split}-{scenes.frames_per_scene}f"
           f"-v{TRIPLANE_CACHE_FORMAT}")
    root = Path(cache_dir) / f"triplanes-{key}"
    layout = plane_fields(encoder.config, scenes.frames_per_scene)
    out: dict[int, Triplane] = {}
    todo = []
    for index in range(len(scenes)):
        payload = read_or_none(root / f"scene{index:05d}.pt", _identity(key, scenes.split, index), layout)
        if payload is None:
            todo.append(index)
        else:
            out[index] = planes_from(payload)
    for index in tqdm(todo, desc=f"encode {scenes.split} scenes", unit="scene", disable=not progress or not todo):
        planes = encode_scene(encoder, scenes.packed(index))
        write_entry(root / f"scene{index:05d}.pt", _identity(key, scenes.split, index), planes_payload(planes))
        out[index] = planes
    return [out[index] for index in range(len(scenes))]


def _identity(key: str, split: str, scene: int) -> dict:
    return {"cache": "triplanes", "key": key, "split": split, "scene": scene}
