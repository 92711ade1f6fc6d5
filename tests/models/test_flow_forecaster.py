"""The flow forecaster: the plane warp, its start as the present frame, its interface."""

from __future__ import annotations

import pytest
import torch

from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.plane_warp import warp_plane
from t3fast.models.triplane import Triplane


def test_integer_flow_moves_the_plane_by_whole_cells():
    plane = torch.randn(2, 3, 12, 9, dtype=torch.float64)
    flow = torch.zeros(2, 2, 12, 9, dtype=torch.float64)
    flow[:, 0] = -2.0  # content comes from two cells back along dim -2: it moves +2 cells
    flow[:, 1] = 1.0  # and one cell back along dim -1
    out = warp_plane(plane, flow)
    assert torch.allclose(out[:, :, 2:, :-1], plane[:, :, :-2, 1:])
    assert torch.allclose(out[:, :, :2, :-1], plane[:, :, :1, 1:].expand(-1, -1, 2, -1))  # the edge continues


def test_fractional_flow_interpolates_and_is_differentiable():
    plane = torch.randn(1, 2, 6, 7, dtype=torch.float64)
    flow = torch.full((1, 2, 6, 7), 0.25, dtype=torch.float64, requires_grad=True)
    out = warp_plane(plane, flow)
    expected = 0.75 * 0.75 * plane[:, :, 2, 3] + 0.25 * 0.75 * (plane[:, :, 3, 3] + plane[:, :, 2, 4]) \
        + 0.0625 * plane[:, :, 3, 4]
    assert torch.allclose(out[:, :, 2, 3], expected)
    torch.autograd.gradcheck(lambda f: warp_plane(plane, f), (flow,))


def test_warp_refuses_a_flow_of_the_wrong_shape():
    with pytest.raises(ValueError, match=r"flow must have shape \[1, 2, 6, 7\]"):
        warp_plane(torch.zeros(1, 2, 6, 7), torch.zeros(1, 2, 7, 6))


def _past(b: int = 2, t: int = 5, c: int = 4, h: int = 20, w: int = 16, z: int = 4) -> Triplane:
    return Triplane(torch.randn(b, t, c, h, w), torch.randn(b, t, c, h, z), torch.randn(b, t, c, w, z))


def test_untrained_forecaster_is_the_present_frame_and_its_body_gets_gradients():
    torch.manual_seed(0)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8, 16), steps=3)
    past = _past()
    futures, flows, deltas = f.predict(past)
    assert len(futures) == 3 and flows.shape == (2, 3, 2, 20, 16) and deltas.shape == (2, 3, 4, 20, 16)
    assert flows.abs().max() < 0.1 and deltas.abs().max() == 0  # a tenth of a cell at most
    for fut in futures:
        assert torch.allclose(fut.xy, past.xy[:, -1], atol=0.3)
        assert torch.equal(fut.xz, past.xz[:, -1]) and torch.equal(fut.yz, past.yz[:, -1])  # carried
    sum(fut.xy.square().sum() for fut in futures).backward()
    assert f.unet.down[0][0].weight.grad.abs().max() > 0  # not a zero head that blocks the body


def test_forecaster_interface_and_its_limits():
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8), steps=3)
    past = _past(b=1)
    futures, changes = f(past, 2)
    assert len(futures) == 2 and torch.allclose(changes[0].xy, futures[0].xy - past.xy[:, -1])
    with pytest.raises(ValueError, match="from the observed history"):
        f(past, 2, first_step=1)
    with pytest.raises(ValueError, match="5 history frames needed, got 3"):
        f.predict(past.map(lambda p: p[:, -3:]))
    with pytest.raises(ValueError, match="at least 2 history frames"):
        FlowTriplaneForecaster(history=1)


@pytest.mark.parametrize("bad, message", [
    (dict(forecaster="lstm"), "'forecaster' must be 'delta' or 'flow'"),
    (dict(flow_widths=[12]), r"'flow_widths\[0\]' must be a multiple of 8"),
    (dict(flow_widths=[]), "'flow_widths' must be a list of 1 to"),
    (dict(flow_scale=0), "'flow_scale' must be a number in"),
])
def test_flow_config_refuses_bad_values(bad, message):
    from t3fast.errors import ConfigError
    from t3fast.models.config import WorldModelConfig

    with pytest.raises(ConfigError, match=message):
        WorldModelConfig(**bad)


def test_world_model_builds_the_forecaster_its_config_names():
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig
    from t3fast.models.world_model import T3Former

    ae = AutoencoderConfig(embed_dim=4, full_res_channels=4, full_res_blocks=0, half_res_channels=8,
                           half_res_blocks=0, channels=4, decoder_channels=8, decoder_hidden=[16])
    world = WorldModelConfig(forecaster="flow", flow_widths=[8, 8], planner_widths=[8, 8, 8, 8], d_act=10,
                             planner_heads=2, ego_aligned=True)
    model = T3Former.from_config(ae, world)
    assert isinstance(model.forecaster, FlowTriplaneForecaster)
    past = Triplane(torch.randn(1, 5, 4, 100, 100), torch.randn(1, 5, 4, 100, 16), torch.randn(1, 5, 4, 100, 16))
    futures, flows, deltas = model(past, torch.zeros(1, 4, 2), motion=True)
    assert len(futures) == 6 and flows.shape == (1, 6, 2, 100, 100)
    futures, _, actions = model.rollout(past, torch.zeros(1, 4, 2), 6)
    assert len(futures) == 6 and actions.shape == (1, 6, 2)
