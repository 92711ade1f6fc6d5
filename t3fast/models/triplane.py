"""The triplane container."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class Triplane(NamedTuple):
    """Three feature planes of one occupancy volume.

    Attributes:
        xy: ``[B, C, X', Y']`` (mean over height).
        xz: ``[B, C, X', Z']`` (mean over y).
        yz: ``[B, C, Y', Z']`` (mean over x).

    Every function that takes a ``Triplane`` also takes a plain ``(xy, xz, yz)`` tuple. A
    BEV-only latent has ``xz`` and ``yz`` set to None.
    """

    xy: Tensor
    xz: Tensor
    yz: Tensor

    def numel_per_sample(self) -> int:
        """Latent size of one sample: C * (X'Y' + X'Z' + Y'Z')."""
        return sum(p[0].numel() for p in self if p is not None)

    def map(self, fn) -> Triplane:
        """Applies ``fn`` to each plane."""
        return Triplane(*(None if p is None else fn(p) for p in self))

    def append(self, frame: Triplane) -> Triplane:
        """A history of planes ``[B, T, C, H, W]`` with ``frame`` (planes ``[B, C, H, W]``) added
        as time step ``T``."""
        return Triplane(*(None if h is None else torch.cat([h, f.unsqueeze(1)], dim=1) for h, f in zip(self, frame)))

    @staticmethod
    def cat(parts: list[Triplane]) -> Triplane:
        """Planes ``[B_i, ...]`` of several batches -> one batch ``[sum B_i, ...]``."""
        return Triplane(*(None if ps[0] is None else torch.cat(ps) for ps in zip(*parts)))

    @staticmethod
    def stack(frames: list[Triplane]) -> Triplane:
        """Planes ``[B, C, H, W]`` of T frames -> one history ``[B, T, C, H, W]``."""
        return Triplane(*(None if ps[0] is None else torch.stack(ps, dim=1) for ps in zip(*frames)))
