"""Write synthetic scenes in the Occ3D-nuScenes layout, readable by ``Occ3DNuScenes``.

Output::

    <out>/gts/<scene>/<token>/labels.npz      # semantics, mask_lidar, mask_camera (uint8)
    <out>/synthetic_infos_<split>.pkl         # {"infos": {scene: [frame, ...]}, "metadata": {...}}

``mask_lidar`` is written equal to ``mask_camera`` (one ray-cast visibility). Boxes and
trajectories are in each frame's ego coordinates, so no ``lidar2ego`` keys are written.

Exports of different splits can share a folder; another export of the same split first
needs the old one removed (:func:`remove_export`), or its frames would be left stale.
"""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from t3fast.data import classes as C
from t3fast.data.route import COMMANDS, route_command
from t3fast.data.synthetic.dataset import PackedScene, SyntheticScenes

FUTURE_STEPS = 6


def info_filename(split: str) -> str:
    return f"synthetic_infos_{split}.pkl"


def _scene_pattern(split: str) -> re.Pattern[str]:
    """The names of the scene folders an export of ``split`` writes under ``gts/``."""
    return re.compile(rf"synthetic-{re.escape(split)}-\d{{5,}}")


def _is_folder(path: Path) -> bool:
    return path.is_dir() and not path.is_symlink()


def existing_export(out: str | Path, split: str) -> list[Path]:
    """What an earlier export of ``split`` left in ``out``: its info file and its scene folders."""
    out = Path(out)
    found = [out / info_filename(split)] if os.path.lexists(out / info_filename(split)) else []
    if _is_folder(out / "gts"):
        pattern = _scene_pattern(split)
        found += sorted(p for p in (out / "gts").iterdir() if pattern.fullmatch(p.name))
    return found


def foreign_entries(out: str | Path) -> list[str]:
    """The entries of ``out`` that no export (of any split) writes."""
    out = Path(out)
    if not out.is_dir():
        return []
    infos = {info_filename(split) for split in ("train", "val", "test")}
    scenes = [_scene_pattern(split) for split in ("train", "val", "test")]
    names = [p.name for p in out.iterdir() if p.name not in infos and p.name != "gts"]
    if (out / "gts").exists():
        if not _is_folder(out / "gts"):
            names.append("gts")
        else:
            names += [f"gts/{p.name}" for p in (out / "gts").iterdir()
                      if not (_is_folder(p) and any(s.fullmatch(p.name) for s in scenes))]
    return sorted(names)


def remove_export(out: str | Path, split: str) -> None:
    """Delete what an export of ``split`` wrote into ``out`` (the info file, every
    ``gts/<scene>/<token>/labels.npz`` and the folders left empty) and nothing else."""
    out = Path(out)
    info = out / info_filename(split)
    if os.path.lexists(info):
        info.unlink()
    for scene in existing_export(out, split):
        if not _is_folder(scene):
            continue
        tokens = re.compile(rf"{re.escape(scene.name)}-\d{{3,}}")
        for frame in scene.iterdir():
            if tokens.fullmatch(frame.name) and _is_folder(frame):
                (frame / "labels.npz").unlink(missing_ok=True)
                _remove_if_empty(frame)
        _remove_if_empty(scene)
    _remove_if_empty(out / "gts")


def _remove_if_empty(folder: Path) -> None:
    if _is_folder(folder) and not any(folder.iterdir()):
        folder.rmdir()


def _yaw_quaternion(yaw: float) -> list[float]:
    return [float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2))]


def _future_offsets(positions: np.ndarray, pose: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-step offsets ``[6, 2]`` of world ``positions [T, 2]`` after frame ``t``, in frame ``t``'s
    coordinates, and the mask of steps that exist in the scene."""
    n = len(positions)
    idx = np.minimum(np.arange(t, t + FUTURE_STEPS + 1), n - 1)
    rot = pose[:2, :2].T
    local = (positions[idx] - pose[:2, 3]) @ rot.T
    mask = (np.arange(t + 1, t + FUTURE_STEPS + 1) < n).astype(np.float32)
    return np.diff(local, axis=0) * mask[:, None], mask


def scene_infos(packed: PackedScene, boxes_world: np.ndarray) -> list[dict]:
    """The info dicts of every frame of a synthetic scene (see ``t3fast.data.occ3d`` for the keys)."""
    name = packed.name
    poses = packed.ego_poses
    frames = []
    for t in range(packed.num_frames):
        yaw = float(np.arctan2(poses[t, 1, 0], poses[t, 0, 0]))
        ego_fut, ego_mask = _future_offsets(poses[:, :2, 3], poses[t], t)
        valid = np.flatnonzero(packed.valid[t])
        agent_fut = np.zeros((len(valid), 2 * FUTURE_STEPS), dtype=np.float32)
        agent_mask = np.zeros((len(valid), FUTURE_STEPS), dtype=np.float32)
        for row, a in enumerate(valid):
            off, m = _future_offsets(boxes_world[:, a, :2], poses[t], t)
            agent_fut[row], agent_mask[row] = off.reshape(-1), m
        frames.append(
            {
                "token": f"{name}-{t:03d}",
                "scene_name": name,
                "frame_idx": t,
                "timestamp": int(t * C.FRAME_DT * 1e6),
                "ego2global_translation": poses[t, :3, 3].tolist(),
                "ego2global_rotation": _yaw_quaternion(yaw),
                "gt_ego_fut_trajs": ego_fut,
                "gt_ego_fut_masks": ego_mask,
                "gt_ego_fut_cmd": np.eye(len(COMMANDS), dtype=np.float32)[int(route_command(torch.tensor(ego_fut)))],
                "gt_boxes": packed.boxes[t, valid],
                "gt_names": np.array([C.CLASS_NAMES[c] for c in packed.labels[valid]]),
                "instance_tokens": np.array([f"{name}-agent{a:05d}" for a in valid]),
                "gt_agent_fut_trajs": agent_fut,
                "gt_agent_fut_masks": agent_mask,
            }
        )
    return frames


def export_synthetic(
    out: str | Path, split: str = "train", num_scenes: int = 10, frames_per_scene: int = 40, progress: bool = True
) -> Path:
    """Generate ``num_scenes`` scenes of ``split`` and write them under ``out``; returns the info path."""
    out = Path(out)
    scenes = SyntheticScenes(split, num_scenes, frames_per_scene)
    infos: dict[str, list[dict]] = {}
    for index in tqdm(range(num_scenes), desc=f"export {split}", unit="scene", disable=not progress):
        raw = scenes.generate(index)
        packed = PackedScene.pack(scenes.name(index), raw)
        frames = scene_infos(packed, raw.boxes_world)
        for t, frame in enumerate(frames):
            d = out / "gts" / packed.name / frame["token"]
            d.mkdir(parents=True, exist_ok=True)
            mask = raw.mask_camera[t].astype(np.uint8)
            np.savez_compressed(d / "labels.npz", semantics=raw.occ[t], mask_lidar=mask, mask_camera=mask)
        infos[packed.name] = frames
    info_path = out / info_filename(split)
    with open(info_path, "wb") as f:
        pickle.dump({"infos": infos, "metadata": {"version": "t3fast-synthetic", "split": split}}, f)
    return info_path
