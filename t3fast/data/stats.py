"""Dataset statistics: class frequencies and height profiles of the labels, and how much the
ego manoeuvres."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import torch

from t3fast.data import classes as C
from t3fast.data.sample import DrivingSample


def class_counts(volumes: Iterable[np.ndarray | torch.Tensor]) -> np.ndarray:
    """Voxel counts per class id ``[256]`` (index 255 = ignore) over label volumes."""
    counts = np.zeros(256, dtype=np.int64)
    for vol in volumes:
        arr = vol.numpy() if isinstance(vol, torch.Tensor) else np.asarray(vol)
        counts += np.bincount(arr.reshape(-1), minlength=256)
    return counts


def format_class_table(counts: np.ndarray) -> str:
    """A printable table: id, name, share of all voxels (%), share of occupied voxels (%)."""
    total = counts.sum()
    occupied = counts[: C.FREE].sum()
    lines = [f"{'id':>3}  {'class':<22}{'% voxels':>10}{'% occupied':>12}"]
    for i, name in enumerate(C.CLASS_NAMES):
        occ_share = "" if i == C.FREE else f"{100 * counts[i] / max(occupied, 1):12.3f}"
        lines.append(f"{i:>3}  {name:<22}{100 * counts[i] / max(total, 1):10.4f}{occ_share}")
    if counts[C.IGNORE]:
        lines.append(f"255  {'ignore':<22}{100 * counts[C.IGNORE] / total:10.4f}")
    missing = [C.CLASS_NAMES[i] for i in range(C.FREE) if counts[i] == 0]
    lines.append(f"total voxels {total:,}; classes absent: {', '.join(missing) if missing else 'none'}")
    return "\n".join(lines)


def height_profile(volumes: Iterable[np.ndarray | torch.Tensor]) -> tuple[np.ndarray, int]:
    """Voxel counts per class and z index ``[18, 16]`` (free included, ignore left out) summed
    over label volumes ``[200, 200, 16]``, and the number of volumes."""
    nz = C.GRID_SHAPE[2]
    profile = np.zeros((C.NUM_CLASSES, nz), dtype=np.int64)
    frames = 0
    for vol in volumes:
        arr = vol.numpy() if isinstance(vol, torch.Tensor) else np.asarray(vol)
        flat = arr.reshape(-1, nz).astype(np.int64)
        keep = flat < C.NUM_CLASSES
        # one bincount over (class, z) pairs
        pairs = (flat * nz + np.arange(nz))[keep]
        profile += np.bincount(pairs, minlength=C.NUM_CLASSES * nz).reshape(C.NUM_CLASSES, nz)
        frames += 1
    return profile, frames


def format_height_profile(profile: np.ndarray, frames: int) -> str:
    """A printable table: per class, mean voxels per frame at each z index (0 = -1.0 to -0.6 m)
    and the median z, then the free share of all voxels."""
    nz = profile.shape[1]
    per_frame = profile / max(frames, 1)
    lines = [f"voxels per frame at each z index ({frames} frames)",
             f"{'class':<22}" + "".join(f"{z:>6}" for z in range(nz)) + f"{'z50':>6}"]
    for i in range(C.FREE):
        if profile[i].sum() == 0:
            continue
        median = int(np.searchsorted(np.cumsum(profile[i]), profile[i].sum() / 2))
        lines.append(f"{C.CLASS_NAMES[i]:<22}" + "".join(f"{v:6.0f}" for v in per_frame[i]) + f"{median:>6}")
    free = profile[C.FREE].sum() / max(profile.sum(), 1)
    lines.append(f"free: {100 * free:.1f} % of voxels")
    return "\n".join(lines)


def constant_velocity_error(sample: DrivingSample) -> float:
    """L2 (m) at 3 s between the true future and constant-velocity extrapolation of the last past action."""
    last = sample.past_actions[-1]
    guess = last * torch.arange(1, sample.future_actions.shape[0] + 1, dtype=torch.float32)[:, None]
    return float(torch.linalg.norm(sample.trajectory[-1] - guess[-1]))


def format_motion_summary(samples: Iterable[DrivingSample]) -> str:
    """Ego speed and manoeuvre summary over samples (how wrong constant velocity is)."""
    errors, speeds, turns = [], [], []
    for s in samples:
        errors.append(constant_velocity_error(s))
        speeds.append(float(torch.linalg.norm(s.future_actions, dim=1).mean()) / C.FRAME_DT)
        heading = torch.atan2(s.future_actions[:, 1], s.future_actions[:, 0].clamp(min=1e-3))
        turns.append(float(heading.abs().max()))
    e, v, h = np.array(errors), np.array(speeds), np.degrees(np.array(turns))
    return (
        f"samples {len(e)}; ego speed mean {v.mean():.1f} m/s (stopped {np.mean(v < 0.5):.0%}); "
        f"turning > 20 deg within 3 s: {np.mean(h > 20):.0%}\n"
        f"constant-velocity L2 at 3 s: mean {e.mean():.2f} m, median {np.median(e):.2f} m, "
        f"> 1 m on {np.mean(e > 1.0):.0%} of samples, > 3 m on {np.mean(e > 3.0):.0%}"
    )
