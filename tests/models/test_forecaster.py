"""DeltaTriplaneForecaster and MotionPlanner: shapes, the Delta wiring, autoregression, gradients."""

from __future__ import annotations

import pytest
import torch

from t3fast.models import DeltaTriplaneForecaster, MotionPlanner, Triplane
from tests.models.test_weight_uses import _OpCount

PLANES = (20, 18, 8)


def past_triplane(batch=2, history=5, channels=8, bev=False, seed=0):
    g = torch.Generator().manual_seed(seed)
    x, y, z = PLANES
    xy = torch.randn(batch, history, channels, x, y, generator=g)
    if bev:
        return Triplane(xy, None, None)
    return Triplane(xy, torch.randn(batch, history, channels, x, z, generator=g),
                    torch.randn(batch, history, channels, y, z, generator=g))


def small_forecaster(**kwargs):
    torch.manual_seed(0)
    return DeltaTriplaneForecaster(channels=8, plane_shape=PLANES, widths=(16, 16, 24, 32, 32), max_tokens=256,
                                   **kwargs)


def test_scales_pick_attention_by_token_count():
    scales = small_forecaster().predictors["xy"].scales
    # T * h * w for xy: 5*20*18, 5*10*9, 5*5*5, 5*3*3, 5*2*2 against 256
    assert [s.full_attention for s in scales] == [False, False, True, True, True]


@pytest.mark.parametrize("bev", [False, True])
def test_forecast_shapes_and_delta_identity_at_init(bev):
    model = small_forecaster(bev=bev)
    past = past_triplane(bev=bev)
    futures, deltas = model(past, steps=6)
    assert len(futures) == len(deltas) == 6
    for nxt in futures:
        for p, ref in zip(nxt, past):
            assert (p is None) == (ref is None)
            if p is not None:
                assert p.shape == ref[:, -1].shape
    # zero-initialised heads and an identity 1x1 fusion: the first step copies the present
    for p, ref in zip(futures[0], past):
        if p is not None:
            torch.testing.assert_close(p, ref[:, -1])


def test_without_delta_the_prediction_is_the_full_state():
    model = small_forecaster(predict_delta=False)
    futures, _ = model(past_triplane(), steps=1)
    assert all(torch.count_nonzero(p) == 0 for p in futures[0])  # the zero-initialised head itself


def test_autoregression_feeds_predictions_back():
    model = small_forecaster()
    for p in model.predictors.parameters():  # leave the zero init so predictions change
        torch.nn.init.normal_(p, std=0.05)
    past = past_triplane()
    futures, _ = model(past, steps=2)
    # the second step sees the first prediction as its newest history frame
    shifted = Triplane(*(torch.cat([h[:, 1:], f.unsqueeze(1)], dim=1) for h, f in zip(past, futures[0])))
    again, _ = model.step(shifted, 1)
    for a, b in zip(again, futures[1]):
        torch.testing.assert_close(a, b)


def test_every_parameter_learns():
    model = small_forecaster()
    futures, deltas = model(past_triplane(), steps=3)
    sum(p.square().sum() for t in futures + deltas for p in t).backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None]
    assert not missing


def test_single_scale_ablation_builds_and_runs():
    model = DeltaTriplaneForecaster(channels=8, plane_shape=PLANES, widths=(16,), max_tokens=256)
    futures, _ = model(past_triplane(), steps=2)
    assert futures[1].xy.shape == (2, 8, 20, 18)


@pytest.mark.parametrize("bev", [False, True])
def test_planner_predicts_one_displacement_per_future(bev):
    torch.manual_seed(0)
    planner = MotionPlanner(channels=8, widths=(8, 16, 16, 32), d_act=20, heads=4, bev=bev)
    past = past_triplane(bev=bev)
    present = Triplane(*(None if p is None else p[:, -1] for p in past))
    futures = [present.map(lambda p, k=k: p + 0.1 * k) for k in range(1, 7)]
    deltas = [present.map(lambda p: torch.full_like(p, 0.1)) for _ in range(6)]
    actions = planner(present, futures, deltas, torch.randn(2, 4, 2))
    assert actions.shape == (2, 6, 2)
    actions.square().sum().backward()
    assert all(p.grad is not None for p in planner.parameters())


def _no_aliases(module, uses):
    return [None] * uses


def _backward_adds(loss: torch.Tensor) -> int:
    with _OpCount() as count:
        loss.backward()
    return count.ops["add"]


@pytest.mark.parametrize("part", ["forecaster", "planner"])
def test_rollout_sums_each_weights_gradient_over_the_steps_at_once(part, monkeypatch):
    """The steps of a rollout read aliases of the weights (weight_uses): the same gradients as
    plain autograd, without its add per weight and step."""
    from t3fast.models import forecaster as forecaster_module
    from t3fast.models import planner as planner_module

    steps = 4
    past = past_triplane().map(torch.Tensor.double)
    present = past.map(lambda p: p[:, -1])
    if part == "forecaster":
        module = small_forecaster().double()
        for p in module.predictors.parameters():
            torch.nn.init.normal_(p, std=0.05)

        def loss():
            futures, deltas = module(past, steps=steps)
            return sum(p.square().sum() for t in futures + deltas for p in t)
        reused = list(module.predictors.parameters())
    else:
        torch.manual_seed(0)
        module = MotionPlanner(channels=8, widths=(8, 16, 16, 32), d_act=20, heads=4).double()
        torch.nn.init.normal_(module.action_out.weight, std=0.1)
        futures = [present.map(lambda p, k=k: p + 0.1 * k) for k in range(1, steps + 1)]

        def loss():
            return module(present, futures, futures, torch.randn(2, 4, 2, dtype=torch.float64,
                                                                 generator=torch.Generator().manual_seed(1))).square().sum()
        reused = list(module.encoder.parameters()) + list(module.decoder.parameters())
    aliased = _backward_adds(loss())
    grads = [p.grad.clone() for p in module.parameters()]
    module.zero_grad()
    monkeypatch.setattr(forecaster_module, "weights_per_use", _no_aliases)
    monkeypatch.setattr(planner_module, "weights_per_use", _no_aliases)
    plain = _backward_adds(loss())
    for g, p in zip(grads, module.parameters()):
        torch.testing.assert_close(g, p.grad, rtol=1e-10, atol=1e-12)
    assert plain - aliased >= (steps - 1) * len(reused), (plain, aliased, len(reused))
