"""Copy&Paste and constant-velocity baselines."""

from __future__ import annotations

import torch

from t3fast.evaluation.baselines import constant_velocity, copy_paste


def test_copy_paste_repeats_the_present_frame():
    past = torch.randint(0, 18, (2, 5, 4, 3, 2), dtype=torch.uint8)
    future = copy_paste(past, steps=6)
    assert future.shape == (2, 6, 4, 3, 2)
    assert all(torch.equal(future[:, k], past[:, -1]) for k in range(6))
    future[0, 0, 0, 0, 0] += 1  # an independent tensor, not a view of the input
    assert not torch.equal(future[:, 0], past[:, -1])


def test_constant_velocity_extrapolates_the_last_displacement():
    past = torch.tensor([[[1.0, 0.0], [2.0, 0.5], [3.0, 1.0], [4.0, -1.0]]])
    plan = constant_velocity(past, steps=6)
    assert plan.shape == (1, 6, 2)
    assert torch.equal(plan.cumsum(1)[0, -1], torch.tensor([24.0, -6.0]))
