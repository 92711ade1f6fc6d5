"""Learning-rate schedule: linear warm-up, then cosine decay to a floor."""

from __future__ import annotations

import math
from collections.abc import Callable


def warmup_cosine(
    total_steps: int, warmup_steps: int, lr: float, min_lr: float = 1e-6
) -> Callable[[int], float]:
    """Factor function for ``torch.optim.lr_scheduler.LambdaLR`` (multiplies the base ``lr``).

    Step ``s`` (the number of optimiser steps taken) gets the learning rate
    ``lr * (s + 1) / (warmup_steps + 1)`` for ``s < warmup_steps`` (so the first step is not
    wasted at zero), ``lr`` at ``s = warmup_steps``, then a half cosine down to ``min_lr`` at
    ``s = total_steps``, and ``min_lr`` after that.
    """
    if lr <= 0:
        raise ValueError(f"warmup_cosine: lr must be positive, got {lr}")
    if warmup_steps < 0 or total_steps < warmup_steps:
        raise ValueError(f"warmup_cosine: need 0 <= warmup_steps <= total_steps, got {warmup_steps}, {total_steps}")

    def factor(step: int) -> float:
        if step < warmup_steps:
            return (step + 1) / (warmup_steps + 1)
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        value = min_lr + (lr - min_lr) * 0.5 * (1.0 + math.cos(math.pi * progress))
        return value / lr

    return factor
