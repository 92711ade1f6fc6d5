"""The random draws of a training step, made so that ``train.cuda_graph`` can replay the step:
a host-side coin toss the trainer can draw before the step (``Task.step_variant``; one graph
each way) or the step itself, and uniform numbers drawn on the device where the host may not
read (a CUDA graph can hold a draw on the device, not a copy from the host)."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.host_syncs import reads_host


def toss(generator: torch.Generator | None = None) -> bool:
    """Heads with probability one half, from ``generator`` (None: the global CPU stream), drawn on
    the host whatever the default device."""
    return bool(torch.rand((), generator=generator, device="cpu") < 0.5)


def uniform(shape: tuple[int, ...], device: torch.device, generator: torch.Generator | None = None) -> Tensor:
    """Uniform numbers in ``[0, 1)`` of ``shape`` for ``device``: from ``generator`` where the
    host may read (:func:`~t3fast.host_syncs.reads_host`: the stream every CPU run has drawn
    from), else on the device from its own generator."""
    if reads_host(device):
        return torch.rand(shape, generator=generator, device=device)
    return torch.rand(shape, device=device)


class CoinToss:
    """A task's per-step coin toss (mirror the batch or not) from ``generator``: :meth:`draw`
    tosses for the next :meth:`take`, which otherwise tosses itself."""

    def __init__(self, generator: torch.Generator) -> None:
        self.generator = generator
        self._next: bool | None = None

    def draw(self) -> bool:
        """Toss for the next :meth:`take` and return the outcome."""
        self._next = toss(self.generator)
        return self._next

    def take(self) -> bool:
        """The outcome :meth:`draw` left for this step, else a new toss."""
        drawn, self._next = self._next, None
        return toss(self.generator) if drawn is None else drawn
