"""Stage-2 training windows: batches of 11-frame windows, their encoded triplanes, and the
frames moved into the present ego frame."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor
from torch.utils.data import Dataset

from t3fast.data.classes import FREE, IGNORE
from t3fast.data.sample import PRESENT, DrivingSample
from t3fast.data.synthetic import SyntheticDriving
from t3fast.models.ego_motion import planar_poses, warp_sequence
from t3fast.models.triplane import Triplane
from t3fast.models.world_model import T3Former


@dataclass
class SequenceBatch:
    """Training windows: ``occ`` uint8 ``[B, 11, X, Y, Z]``; ``planes`` the frames' encoded
    triplanes ``[B, 11, C, H, W]`` (None: encode ``occ`` in the step); actions ``[B, 4, 2]``
    and ``[B, 6, 2]`` (present frame); the frames' poses."""

    occ: Tensor
    planes: Triplane | None
    past_actions: Tensor
    future_actions: Tensor
    ego_poses: Tensor  # ``[B, 11, 4, 4]`` ego -> world

    def to(self, device: torch.device | str) -> SequenceBatch:
        planes = None if self.planes is None else self.planes.map(lambda p: p.to(device))
        moved = {f.name: getattr(self, f.name).to(device) for f in fields(self) if f.name != "planes"}
        return SequenceBatch(planes=planes, **moved)


class EncodedWindows(Dataset):
    """Synthetic windows with their frames' triplanes from a per-scene cache."""

    def __init__(self, windows: SyntheticDriving, planes: list[Triplane]):
        self.windows, self.planes = windows, planes

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> tuple[DrivingSample, Triplane]:
        sample = self.windows[index]
        scene, start = self.windows.locate(index)
        window = slice(start, start + sample.occ.shape[0])
        return sample, self.planes[scene].map(lambda p: p[window].float())


def collate_windows(items: list) -> SequenceBatch:
    """Items are ``DrivingSample``s or ``(DrivingSample, Triplane)`` pairs."""
    pairs = [item if isinstance(item, tuple) else (item, None) for item in items]
    samples = [s for s, _ in pairs]
    planes = None
    if pairs[0][1] is not None:
        per_plane = zip(*(t for _, t in pairs))
        planes = Triplane(*(None if first is None else torch.stack(ps) for first, ps in zip(pairs[0][1], per_plane)))
    return SequenceBatch(
        occ=torch.stack([s.occ for s in samples]),
        planes=planes,
        past_actions=torch.stack([s.past_actions for s in samples]),
        future_actions=torch.stack([s.future_actions for s in samples]),
        ego_poses=torch.stack([s.ego_poses for s in samples]),
    )


@torch.no_grad()
def moved_window(occ: Tensor, ego_poses: Tensor) -> Tensor:
    """The frames of windows ``occ`` ``[B, 11, X, Y, Z]`` (poses ``[B, 11, 4, 4]``) moved into
    the present ego frame, ``IGNORE`` where a frame did not see that part of the present grid."""
    return warp_sequence(occ, planar_poses(ego_poses, PRESENT), fill=IGNORE)


def ego_aligned_window(
    model: T3Former, occ: Tensor, ego_poses: Tensor, frames: Sequence[int] | None = None
) -> tuple[Triplane, Tensor]:
    """The 11 frames of windows ``occ`` ``[B, 11, X, Y, Z]`` moved into the present ego frame
    (poses ``[B, 11, 4, 4]``): (their encoded planes ``[B, 11, C, H, W]``, the moved labels with
    ``IGNORE`` where a frame did not see that part of the present grid).

    The past frames are encoded as at inference
    (:meth:`~t3fast.forecast.encode.EncodePast.planes`: what a past frame did not see is free).
    A future frame's target keeps the present frame's content where that future frame did not
    look: the static world does not vanish behind the ego.
    ``frames``: encode only these (a rollout reads a few; encoding is half a step's cost), the
    planes of the others stay zero.
    """
    moved = moved_window(occ, ego_poses)
    unseen = moved == IGNORE
    history = moved[:, : PRESENT + 1].masked_fill(unseen[:, : PRESENT + 1], FREE)
    future = torch.where(unseen[:, PRESENT + 1 :], occ[:, PRESENT : PRESENT + 1], moved[:, PRESENT + 1 :])
    inputs = torch.cat([history, future], dim=1)
    if frames is None:
        return model.encode_sequence(inputs), moved
    index = torch.tensor(sorted(set(frames)), device=occ.device)
    encoded = model.encode_sequence(inputs[:, index])

    def scatter(p: Tensor) -> Tensor:
        full = p.new_zeros(p.shape[0], occ.shape[1], *p.shape[2:])
        full[:, index] = p
        return full

    return encoded.map(scatter), moved


def rollout_frames(first: int, steps: int, pushforward: bool) -> list[int]:
    """Window frames a rollout of ``steps`` steps from future step ``first`` reads: the past
    and present, the encoded future frames it starts from (none with pushforward: its own
    predictions), and its targets."""
    start = PRESENT + 1 + (first if pushforward else 0)
    return list(range(PRESENT + 1)) + list(range(start, PRESENT + 1 + first + steps))
