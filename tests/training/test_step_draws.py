"""The random draws of a training step: the per-step coin toss a task draws for ``train.cuda_graph``
before the step, or the step itself."""

from __future__ import annotations

import torch

from t3fast.training.step_draws import CoinToss


def test_the_step_takes_the_toss_drawn_for_it_else_tosses_itself_from_the_same_stream():
    coin = CoinToss(torch.Generator().manual_seed(5))
    drawn = [coin.draw() for _ in range(3)]  # each draw replaces the one before
    assert coin.take() == drawn[-1]
    plain = torch.Generator().manual_seed(5)
    expected = [bool(torch.rand((), generator=plain) < 0.5) for _ in range(24)]
    taken = []
    for i in range(20):
        taken.append(coin.draw() if i % 2 else coin.take())
        if i % 2:
            assert coin.take() == taken[-1]
    assert taken == expected[3:23] and len(set(taken)) == 2
