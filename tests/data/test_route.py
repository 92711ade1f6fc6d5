"""The route command: derived from where the ego is 3 s ahead, mirrored with the window."""

from __future__ import annotations

import pytest
import torch

from t3fast.data.route import LEFT, RIGHT, STRAIGHT, TURN_OFFSET, mirror_command, route_command
from t3fast.data.sample import collate_samples, flip_sample


def _ahead(lateral: float) -> torch.Tensor:
    """Six 2 m steps forward ending ``lateral`` metres to the left."""
    actions = torch.zeros(6, 2)
    actions[:, 0] = 2.0
    actions[3:, 1] = lateral / 3
    return actions


@pytest.mark.parametrize(("lateral", "command"), [
    (0.0, STRAIGHT), (TURN_OFFSET - 0.1, STRAIGHT), (-TURN_OFFSET + 0.1, STRAIGHT),
    (TURN_OFFSET, LEFT), (8.0, LEFT), (-TURN_OFFSET, RIGHT), (-8.0, RIGHT),
])
def test_the_command_is_the_lateral_offset_3_s_ahead(lateral, command):
    assert int(route_command(_ahead(lateral))) == command


def test_commands_of_a_batch_and_bad_input():
    batch = torch.stack([_ahead(5.0), _ahead(-5.0), _ahead(0.5)])
    assert route_command(batch).tolist() == [LEFT, RIGHT, STRAIGHT]
    assert mirror_command(route_command(batch)).tolist() == [RIGHT, LEFT, STRAIGHT]
    with pytest.raises(ValueError, match=r"future_actions must be \[..., steps, 2\], got \[6, 3\]"):
        route_command(torch.zeros(6, 3))


def test_samples_carry_the_command_and_mirroring_left_right_swaps_it(synthetic):
    samples = [synthetic[i] for i in range(len(synthetic))]
    for s in samples:
        assert s.command.dtype == torch.int64 and s.command.shape == ()
        assert torch.equal(s.command, route_command(s.future_actions))
        mirrored = flip_sample(s, "y")
        assert torch.equal(mirrored.command, route_command(mirrored.future_actions))
        assert torch.equal(flip_sample(s, "x").command, s.command)  # x -> -x keeps the lateral offset
    assert torch.equal(collate_samples(samples).command, torch.stack([s.command for s in samples]))
