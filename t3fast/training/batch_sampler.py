"""Batches that a resumed run can pick up mid-epoch."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch.utils.data import Sampler

from t3fast.training.random_state import derive_seed


class ResumableBatchSampler(Sampler[list[int]]):
    """Deterministic, sharded, resumable batches of dataset indices.

    Epoch ``e`` draws one permutation from a generator seeded by ``(seed, e)``. Global batch
    ``b`` is ``perm[b*G:(b+1)*G]`` with ``G = batch_size * world_size``; rank ``r`` takes its
    ``r``-th slice of ``batch_size``. The incomplete tail is dropped so every rank takes the
    same number of steps. ``set_epoch(e, skip)`` starts the epoch at batch ``skip``.
    """

    def __init__(self, dataset_size: int, batch_size: int, seed: int, rank: int = 0, world_size: int = 1) -> None:
        self.dataset_size, self.batch_size, self.seed = dataset_size, batch_size, seed
        self.rank, self.world_size = rank, world_size
        self.batches_per_epoch = dataset_size // (batch_size * world_size)
        if self.batches_per_epoch == 0:
            raise ValueError(
                f"dataset of {dataset_size} samples is smaller than one global batch "
                f"({batch_size} per process x {world_size} processes)"
            )
        self.epoch, self.skip = 0, 0

    def set_epoch(self, epoch: int, skip: int = 0) -> None:
        """Choose the epoch to iterate and how many of its batches were already consumed."""
        self.epoch, self.skip = epoch, skip

    def __len__(self) -> int:
        return self.batches_per_epoch - self.skip

    def __iter__(self) -> Iterator[list[int]]:
        gen = torch.Generator().manual_seed(derive_seed(self.seed, self.epoch))
        perm = torch.randperm(self.dataset_size, generator=gen).tolist()
        global_batch = self.batch_size * self.world_size
        for b in range(self.skip, self.batches_per_epoch):
            start = b * global_batch + self.rank * self.batch_size
            yield perm[start : start + self.batch_size]
