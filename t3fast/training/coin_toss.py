"""A task's per-step coin toss (mirror the batch or not) that ``train.cuda_graph`` can replay: the
trainer draws it before the step (``Task.step_variant``; one graph each way), or the step draws it
itself, from the task's own generator either way."""

from __future__ import annotations

import torch


class CoinToss:
    """Heads with probability one half, from ``generator``; :meth:`draw` tosses for the next
    :meth:`take`, which otherwise tosses itself."""

    def __init__(self, generator: torch.Generator) -> None:
        self.generator = generator
        self._next: bool | None = None

    def draw(self) -> bool:
        """Toss for the next :meth:`take` and return the outcome."""
        self._next = self._toss()
        return self._next

    def take(self) -> bool:
        """The outcome :meth:`draw` left for this step, else a new toss."""
        drawn, self._next = self._next, None
        return self._toss() if drawn is None else drawn

    def _toss(self) -> bool:
        return bool(torch.rand((), generator=self.generator) < 0.5)
