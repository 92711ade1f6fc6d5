"""The constant-turn-rate plan (the untrained planner's plan and a baseline): its closed form is
``continue_motion`` applied step after step."""

from __future__ import annotations

import math

import torch

from t3fast.models.planner import constant_turn_rate, continue_motion


def _iterated(past: torch.Tensor, steps: int) -> torch.Tensor:
    """The definition: each displacement continues the motion of the ones before it."""
    actions, out = past, []
    for _ in range(steps):
        out.append(continue_motion(actions))
        actions = torch.cat([actions, out[-1].unsqueeze(1)], dim=1)
    return torch.stack(out, dim=1)


def test_constant_turn_rate_is_continue_motion_step_after_step():
    g = torch.Generator().manual_seed(0)
    past = torch.randn(64, 4, 2, generator=g, dtype=torch.float64) * 3
    past[:8] *= 0.01  # slow: below min_step the heading is noise, the last step is kept
    past[8:16, -2] *= 0.01  # only the one before the last is slow
    got = constant_turn_rate(past, 6)
    assert got.shape == (64, 6, 2)
    torch.testing.assert_close(got, _iterated(past, 6), rtol=1e-12, atol=1e-12)
    assert torch.equal(got[:16], past[:16, -1:].expand(-1, 6, -1))


def test_constant_turn_rate_continues_an_arc():
    angles = torch.tensor([0.0, 0.1, 0.2, 0.3])
    past = 2.0 * torch.stack([angles.cos(), angles.sin()], -1)[None]
    future = constant_turn_rate(past, 3)[0]
    want = torch.tensor([0.4, 0.5, 0.6])
    torch.testing.assert_close(torch.atan2(future[:, 1], future[:, 0]), want)
    torch.testing.assert_close(future.norm(dim=-1), torch.full((3,), 2.0))
    # one past displacement: nothing to turn by
    one = constant_turn_rate(past[:, :1], 2)
    assert torch.equal(one, past[:, :1].expand(-1, 2, -1)) and not math.isnan(one.sum().item())
