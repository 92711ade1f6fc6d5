"""The route planner: constant turn rate untrained, reads the road ahead and the command, learns."""

from __future__ import annotations

import pytest
import torch

from t3fast.data.route import LEFT, RIGHT, STRAIGHT
from t3fast.errors import ConfigError, UsageError
from t3fast.models.planner import constant_turn_rate
from t3fast.models.route_planner import RoutePlanner, ahead_window


def _inputs(b: int = 3):
    torch.manual_seed(0)
    present, previous = torch.randn(b, 4, 100, 100), torch.randn(b, 4, 100, 100)
    past = torch.tensor([[2.0, 0.0], [2.0, 0.1], [2.0, 0.2], [2.0, 0.3]]).expand(b, 4, 2).clone()
    return present, previous, past


def _trained(planner: RoutePlanner) -> RoutePlanner:
    torch.nn.init.normal_(planner.head[-1].weight, std=0.1)  # a trained head's correction
    return planner


def test_untrained_route_planner_is_constant_turn_rate_and_learns_from_step_one():
    present, previous, past = _inputs()
    planner = RoutePlanner(4, (100, 100))
    planned = planner(present, previous, past, torch.tensor([LEFT, RIGHT, STRAIGHT]))
    assert torch.allclose(planned, constant_turn_rate(past, 6))
    planned.square().sum().backward()
    assert planner.head[-1].weight.grad.abs().sum() > 0


def test_route_planner_reads_the_command_and_the_road_ahead_only():
    present, previous, past = _inputs()
    planner = _trained(RoutePlanner(4, (100, 100)))
    with torch.no_grad():
        left = planner(present, previous, past, torch.full((3,), LEFT))
        right = planner(present, previous, past, torch.full((3,), RIGHT))
        assert not torch.allclose(left, right)
        # no command for any window, or -1 for each: the same plan
        assert torch.equal(planner(present, previous, past, None), planner(present, previous, past,
                                                                           torch.full((3,), -1)))
        rows, cols = ahead_window((100, 100))
        assert (rows.start, rows.stop, cols.start, cols.stop) == (40, 100, 20, 80)  # -8..40 m, -24..24 m
        ahead, behind = present.clone(), present.clone()
        ahead[:, :, 70, 50] += 5.0  # 16 m ahead of the ego
        behind[:, :, 20, 50] += 5.0  # 24 m behind it: outside the window
        base = planner(present, previous, past, None)
        assert not torch.allclose(planner(ahead, previous, past, None), base)
        assert torch.equal(planner(behind, previous, past, None), base)
    with pytest.raises(ValueError, match="reads 4 past displacements, got 2"):
        planner(present, previous, past[:, :2])


def test_route_planner_learns_what_the_command_says():
    """Windows alike but for the command: the ego turns 4 m left or right of constant turn rate
    at 3 s, or goes on; a few hundred steps bring the error well below constant turn rate's."""
    torch.manual_seed(0)
    present, previous, past = _inputs(6)
    command = torch.tensor([LEFT, RIGHT, STRAIGHT] * 2)
    future = constant_turn_rate(past, 6).clone()
    future[:, 3:, 1] += torch.tensor([4.0, -4.0, 0.0] * 2)[:, None] / 3
    planner = RoutePlanner(4, (100, 100))
    opt = torch.optim.Adam(planner.parameters(), 3e-3)

    def error(planned):
        return (planned.cumsum(1) - future.cumsum(1)).norm(dim=-1).mean()

    with torch.no_grad():
        start = float(error(planner(present, previous, past, command)))
    for _ in range(150):
        loss = error(planner(present, previous, past, command))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss.item() < 0.3 * start, (start, loss.item())


def test_route_planner_config_and_the_world_models_command_checks():
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig
    from t3fast.models.world_model import T3Former

    with pytest.raises(ConfigError, match="'planner' must be 'phi_act' or 'route', got 'vad'"):
        WorldModelConfig(planner="vad")
    with pytest.raises(ConfigError, match="'planner'='route' .* needs ego_aligned=true"):
        WorldModelConfig(planner="route")
    with pytest.raises(ConfigError, match=r"'route_modes' must be an integer in \[1, 16\], got 0"):
        WorldModelConfig(route_modes=0)
    ae = AutoencoderConfig(embed_dim=4, full_res_channels=4, full_res_blocks=0, half_res_channels=8,
                           half_res_blocks=0, channels=4, decoder_channels=8, decoder_hidden=[16])
    world = WorldModelConfig(forecaster="flow", flow_widths=[8, 8], ego_aligned=True,
                             render_agents=True, planner="route")
    model = T3Former.from_config(ae, world).eval()
    assert model.reads_command and isinstance(model.planner, RoutePlanner)
    occ = torch.zeros(2, 5, 200, 200, 16, dtype=torch.uint8)
    motion = torch.tensor([2.0, 0.0]).expand(2, 4, 2)
    untrained = model.forecast(occ, motion, command=torch.tensor([LEFT, RIGHT]))
    assert torch.allclose(untrained.actions, constant_turn_rate(motion, 6))
    assert torch.equal(model.forecast(occ, motion).actions, untrained.actions)  # works without one
    _trained(model.planner)
    turned = model.forecast(occ, motion, command=torch.tensor([LEFT, LEFT])).actions
    assert not torch.allclose(turned, model.forecast(occ, motion, command=torch.tensor([RIGHT, RIGHT])).actions)
    with pytest.raises(UsageError, match=r"route commands int64 \[B\] with B = 2, got torch.int64 \[3\]"):
        model.forecast(occ, motion, command=torch.tensor([0, 1, 2]))
    with pytest.raises(UsageError, match="command values must be in 0..2 .*, got 3"):
        model.forecast(occ, motion, command=torch.tensor([1, 3]))
    phi_act = T3Former.from_config(ae, WorldModelConfig(forecaster="flow", flow_widths=[8, 8], planner_widths=[8] * 4,
                                                        d_act=10, planner_heads=2, ego_aligned=True)).eval()
    assert not phi_act.reads_command
    with pytest.raises(UsageError, match="planner does not read a route command"):
        phi_act.forecast(occ, motion, command=torch.tensor([1, 2]))
