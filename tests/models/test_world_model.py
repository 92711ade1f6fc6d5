"""T3Former wiring: the forecasting step end to end on a tiny grid."""

from __future__ import annotations

import dataclasses

import torch

from t3fast.models import DeltaTriplaneForecaster, MotionPlanner, TriplaneDecoder, TriplaneEncoder
from t3fast.models.world_model import T3Former

from .test_autoencoder import TINY, random_labels


def tiny_world_model() -> T3Former:
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, grid=(16, 12, 4))
    return T3Former(
        TriplaneEncoder(cfg),
        DeltaTriplaneForecaster(channels=cfg.channels, plane_shape=cfg.plane_shape, widths=(8, 8, 16), max_tokens=64),
        MotionPlanner(channels=cfg.channels, widths=(8, 8, 16, 16), d_act=20, heads=4),
        TriplaneDecoder.from_config(cfg),
    )


def test_forecast_shapes_and_types():
    model = tiny_world_model().eval()
    past = torch.stack([random_labels(2, (16, 12, 4), seed=s) for s in range(5)], dim=1)
    out = model.forecast(past, torch.randn(2, 4, 2), steps=6)
    assert out.labels.shape == (2, 6, 16, 12, 4) and out.labels.dtype == torch.uint8
    assert len(out.triplanes) == 6 and out.triplanes[0].xy.shape == (2, 8, 8, 6)
    assert out.actions.shape == (2, 6, 2)
    torch.testing.assert_close(out.trajectory, out.actions.cumsum(1))


def test_encoder_stays_frozen_in_training_mode():
    model = tiny_world_model().train()
    assert not model.encoder.training
    assert not any(p.requires_grad for p in model.encoder.parameters())
    past = torch.stack([random_labels(1, (16, 12, 4), seed=s) for s in range(5)], dim=1)
    futures, _, actions = model.rollout(model.encode_sequence(past), torch.randn(1, 4, 2), steps=2)
    loss = actions.square().sum() + sum(p.square().sum() for p in futures[-1])
    loss.backward()
    assert all(p.grad is None for p in model.encoder.parameters())
    assert any(p.grad is not None for p in model.forecaster.parameters())


def test_training_rollout_from_a_later_step_decodes_points():
    model = tiny_world_model().train()
    past = model.encode_sequence(torch.stack([random_labels(2, (16, 12, 4), seed=s) for s in range(5)], dim=1))
    points = [torch.rand(2, 30, 3) * 2 - 1 for _ in range(3)]
    futures, actions, logits = model(past, torch.randn(2, 6, 2), steps=3, first_step=2, points=points)
    assert len(futures) == 3 and actions.shape == (2, 3, 2)
    assert [tuple(x.shape) for x in logits] == [(2, 30, 18)] * 3
    # rollouts are reproducible and use the per-step queries of steps 2..4
    again = model(past, torch.randn(2, 6, 2), steps=1, first_step=2)[0][0]
    torch.testing.assert_close(again.xy, futures[0].xy)


def test_forecaster_outputs_are_contiguous_nchw():
    """Channels-last planes leaking out of the forecaster made the planner's conv weight
    gradient abort with heap corruption (oneDNN, torch 2.13 CPU); keep them NCHW."""
    model = tiny_world_model()
    past = model.encode_sequence(torch.stack([random_labels(1, (16, 12, 4), seed=s) for s in range(5)], dim=1))
    futures, deltas = model.forecaster(past, 2)
    assert all(p.is_contiguous() for t in futures + deltas for p in t)


def test_planning_loss_trains_the_planner_not_the_forecaster():
    model = tiny_world_model().train()
    past = model.encode_sequence(torch.stack([random_labels(2, (16, 12, 4), seed=s) for s in range(5)], dim=1))
    _, actions, _ = model(past, torch.randn(2, 4, 2), steps=2)
    actions.square().sum().backward()
    assert all(p.grad is None for p in model.forecaster.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.planner.parameters())
