"""Training sets whose batches are gathered whole from tensors held in memory: on the GPU where
they fit, so a step reads nothing from disk or the host and copies nothing to the device;
otherwise in host memory. Either way a batch comes out already collated (``__getitems__``):
one gather per field, not one slice per item stacked again.

A task whose :meth:`~t3fast.training.task.Task.train_dataset` returns one of these collates
nothing (its ``collate`` passes the batch on), and the trainer reads ``device`` to know where
the batches are: held on the GPU, the loader has no workers (they cannot touch the GPU) and
pins nothing.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from torch.utils.data import Dataset


def fits_on(device: torch.device, size: int, share: float = 0.25) -> bool:
    """Whether ``size`` bytes are at most ``share`` of a GPU's free memory (the rest is the
    model's, its activations' and the allocator's); never on the CPU, where the data stays in
    host memory."""
    return device.type == "cuda" and size <= share * torch.cuda.mem_get_info(device)[0]


def held_on_device(dataset: object) -> bool:
    """Whether ``dataset`` makes its batches on an accelerator (its ``device`` attribute)."""
    device = getattr(dataset, "device", None)
    return device is not None and torch.device(device).type != "cpu"


def nbytes(tensors: dict[str, Tensor]) -> int:
    """The memory ``tensors`` take."""
    return sum(t.numel() * t.element_size() for t in tensors.values())


class GatheredBatches(Dataset):
    """Rows of ``fields`` (tensors with one row per item, the same number each), held on
    ``device`` when they fit there (:func:`fits_on`) and in host memory otherwise; a batch is
    gathered where they are and made by :meth:`batch`.

    Attributes: ``target``, the device the batches are for (the training device); ``device``,
    where the fields are held and the batches made (``target`` or the CPU).
    """

    def __init__(self, fields: dict[str, Tensor], device: torch.device | str = "cpu"):
        sizes = {name: t.shape[0] for name, t in fields.items()}
        if len(set(sizes.values())) != 1:
            raise ValueError(f"{type(self).__name__}: every field needs one row per item, got {sizes}")
        self.target = torch.device(device)
        self.device = self.target if fits_on(self.target, nbytes(fields)) else torch.device("cpu")
        self.fields = {name: t.to(self.device) for name, t in fields.items()}

    def __len__(self) -> int:
        return next(iter(self.fields.values())).shape[0]

    def __getitems__(self, indices: list[int]) -> Any:
        """The batch of the items ``indices``, collated (the DataLoader fetches a batch through this)."""
        return self.take(torch.as_tensor(indices, device=self.device))

    def take(self, index: Tensor) -> Any:
        """The batch of the items at ``index`` (int64 ``[B]``, on :attr:`device`)."""
        return self.batch({name: t[index] for name, t in self.fields.items()})

    def all(self) -> Any:
        """Every item in one batch."""
        return self.take(torch.arange(len(self), device=self.device))

    def batch(self, rows: dict[str, Tensor]) -> Any:
        """The task's batch from the gathered ``rows`` of every field; the rows themselves by default."""
        return rows
