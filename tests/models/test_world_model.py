"""T3Former wiring: the forecasting step end to end on a tiny grid."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from t3fast.errors import UsageError
from t3fast.forecast.encode import encode_sequence
from t3fast.forecast.plan import planned_poses
from t3fast.forecast.render import observed_static, present_in_frames
from t3fast.host_syncs import sync_free
from t3fast.models import DeltaTriplaneForecaster, MotionPlanner, TriplaneDecoder, TriplaneEncoder
from t3fast.models.ego_motion import poses_from_displacements
from t3fast.models.planner import constant_turn_rate
from t3fast.models.world_model import T3Former
from t3fast.training.world_model.forwards import RolloutModel

from .test_autoencoder import TINY, random_labels


def tiny_world_model(cls: type[T3Former] = T3Former, **layout: bool) -> T3Former:
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, grid=(16, 12, 4))
    return cls(
        TriplaneEncoder(cfg),
        DeltaTriplaneForecaster(channels=cfg.channels, plane_shape=cfg.plane_shape, widths=(8, 8, 16), max_tokens=64),
        MotionPlanner(channels=cfg.channels, widths=(8, 8, 16, 16), d_act=20, heads=4),
        TriplaneDecoder.from_config(cfg),
        **layout,
    )


def test_forecast_shapes_and_types():
    model = tiny_world_model().eval()
    past = torch.stack([random_labels(2, (16, 12, 4), seed=s) for s in range(5)], dim=1)
    out = model.forecast(past, torch.randn(2, 4, 2), steps=6)
    assert out.labels.shape == (2, 6, 16, 12, 4) and out.labels.dtype == torch.uint8
    assert len(out.triplanes) == 6 and out.triplanes[0].xy.shape == (2, 8, 8, 6)
    assert out.actions.shape == (2, 6, 2)
    torch.testing.assert_close(out.trajectory, out.actions.cumsum(1))


@pytest.mark.parametrize("per_call", [32, 4])
def test_frames_encoded_together_as_on_an_accelerator_give_the_frame_by_frame_planes(monkeypatch, per_call):
    """All six frames in one call, or in calls of four frames and two."""
    monkeypatch.setattr("t3fast.forecast.encode.FRAMES_PER_CALL", per_call)
    encoder = tiny_world_model().encoder.eval()
    occupancy = torch.stack([random_labels(2, (16, 12, 4), seed=s) for s in range(3)], dim=1)  # [2, 3, X, Y, Z]
    one_call = encode_sequence(encoder, occupancy, frame_by_frame=False)
    by_frame = encode_sequence(encoder, occupancy)
    assert one_call.xy.shape == by_frame.xy.shape == (2, 3, *by_frame.xy.shape[2:])
    for a, b in zip(one_call, by_frame):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(one_call.xz[1, 2], encoder(occupancy[1:, 2]).xz[0], atol=1e-5, rtol=1e-5)


def test_the_cpu_encodes_each_windows_frame_alone_and_the_gpus_code_keeps_the_batch(monkeypatch):
    """On the CPU's own path a call per window and time step, whose planes are each window's
    encoded alone, exactly; the GPU's code (``sync_free``) encodes a time step of the batch per call."""
    encoder = tiny_world_model().encoder.eval()
    occupancy = torch.stack([random_labels(3, (16, 12, 4), seed=s) for s in range(2)], dim=1)  # [3, 2, X, Y, Z]
    batches, forward = [], type(encoder).forward
    monkeypatch.setattr(type(encoder), "forward", lambda self, x: batches.append(len(x)) or forward(self, x))
    planes = encode_sequence(encoder, occupancy)
    assert batches == [1] * 6
    for w in range(3):
        alone = encode_sequence(encoder, occupancy[w : w + 1])
        assert all(torch.equal(a[w : w + 1], b) for a, b in zip(planes, alone))
    batches.clear()
    with sync_free():
        encode_sequence(encoder, occupancy)
    assert batches == [3, 3]


def test_encoder_stays_frozen_in_training_mode():
    model = tiny_world_model(RolloutModel).train()
    assert not model.encoder.training
    assert not any(p.requires_grad for p in model.encoder.parameters())
    past = torch.stack([random_labels(1, (16, 12, 4), seed=s) for s in range(5)], dim=1)
    futures, actions = model.rollout(model.encode_sequence(past), torch.randn(1, 4, 2), steps=2)
    loss = actions.square().sum() + sum(p.square().sum() for p in futures[-1])
    loss.backward()
    assert all(p.grad is None for p in model.encoder.parameters())
    assert any(p.grad is not None for p in model.forecaster.parameters())


def test_training_rollout_from_a_later_step_decodes_points():
    model = tiny_world_model(RolloutModel).train()
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
    model = tiny_world_model(RolloutModel).train()
    past = model.encode_sequence(torch.stack([random_labels(2, (16, 12, 4), seed=s) for s in range(5)], dim=1))
    _, actions, _ = model(past, torch.randn(2, 4, 2), steps=2)
    actions.square().sum().backward()
    assert all(p.grad is None for p in model.forecaster.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.planner.parameters())


def aligned() -> T3Former:
    """The ego-aligned model with decoded frames only (``observed_static`` is tested on its own)."""
    return tiny_world_model(ego_aligned=True, static_from_present=False)


def _past(b: int = 1) -> torch.Tensor:
    return torch.stack([random_labels(b, (16, 12, 4), seed=s) for s in range(5)], dim=1)


def test_aligned_forecast_of_a_standing_ego_is_the_own_frame_forecast():
    # no ego motion: moving frames between ego frames is the identity, so both formulations agree
    past = _past(2)
    still = torch.eye(4).repeat(2, 5, 1, 1)
    own = tiny_world_model().eval().forecast(past, still, future_actions=torch.zeros(2, 3, 2))
    ours = aligned().eval().forecast(past, still, future_actions=torch.zeros(2, 3, 2))
    assert torch.equal(own.labels, ours.labels)


def test_steered_forecast_moves_the_scene_with_the_given_motion():
    model = aligned().eval()
    past = _past()
    still = torch.eye(4).repeat(1, 5, 1, 1)
    present = model.decoder.predict(model.encode_sequence(past).map(lambda p: p[:, -1]))  # [1, 16, 12, 4]
    # 0.8 m = 2 voxels forward per step; Delta = 0 untrained, so step k is the present moved by 2k voxels
    out = model.forecast(past, still, future_actions=torch.tensor([[[0.8, 0.0]] * 3]))
    assert out.poses.shape == (1, 3, 3) and torch.allclose(out.poses[0, :, 0], torch.tensor([0.8, 1.6, 2.4]))
    for k in range(1, 4):
        assert torch.equal(out.labels[0, k - 1, : 16 - 2 * k], present[0, 2 * k :])
        # beyond the present grid the planes continue their edge: the last column repeated
        assert torch.equal(out.labels[0, k - 1, 16 - 2 * k :], present[0, -1:].expand(2 * k, -1, -1))


def test_past_displacements_stand_in_for_poses():
    model = aligned().eval()
    past = _past()
    poses = torch.eye(4).repeat(1, 5, 1, 1)
    poses[0, :, 0, 3] = torch.tensor([-3.2, -2.4, -1.6, -0.8, 0.0])  # straight ahead, 0.8 m per step
    by_poses = model.forecast(past, poses, steps=2)
    by_actions = model.forecast(past, torch.tensor([[[0.8, 0.0]] * 4]), steps=2)
    assert torch.equal(by_poses.labels, by_actions.labels)
    torch.testing.assert_close(by_poses.actions, by_actions.actions)


def test_observed_static_keeps_the_observed_world_and_the_forecast_agents():
    present = torch.full((1, 16, 12, 4), 17, dtype=torch.uint8)
    present[..., 0] = 11  # road
    present[:, 3, :, 1:] = 15  # a thin wall ...
    present[:, 8, 5, 1] = 4  # a car ...
    reference = present.clone()
    reference[:, 3, :, 1:] = 17  # ... the latent lost
    decoded = reference.clone()
    decoded[:, 8, 5, 1] = 17
    decoded[:, 9, 5, 1] = 4  # ... that the forecast moved one cell on
    decoded[:, 3, 2, 1] = 4  # a car the forecast put into the wall
    decoded[:, 12, 7, 2] = 16  # a tree that is not an agent's change
    decoded[:, -1, :, 2] = 16  # a tree at the forecast's edge
    in_place = present_in_frames(present, torch.zeros(1, 1, 3))  # a standing ego
    still = observed_static(decoded[:, None], reference[:, None], in_place)[:, 0]
    assert (still[:, 3, :, 1:] == 15).all()  # the wall as observed, the car refused there
    assert still[0, 9, 5, 1] == 4 and still[0, 8, 5, 1] == 17  # the car where the forecast put it
    assert still[0, 12, 7, 2] == 17 and (still[0, -1, :, 2] == 17).all()  # only agents' changes edit
    unchanged = observed_static(reference[:, None], reference[:, None], in_place)[:, 0]
    assert torch.equal(unchanged, present)  # no predicted change: the present frame exactly
    # 0.8 m on (2 columns): the last 2 columns are beyond the present grid; what the forecast
    # continues there is kept for the road and dropped (free) for everything else
    moved_on = torch.tensor([[[0.8, 0.0, 0.0]]])
    on = observed_static(decoded[:, None], reference[:, None], present_in_frames(present, moved_on))
    assert (on[0, 0, -2:, :, 0] == 11).all() and (on[0, 0, -2:, :, 2] == 17).all()
    assert (on[0, 0, 1, :, 1:] == 15).all()  # the wall moved back with the ego's motion


def test_planned_headings_continue_the_observed_yaw_rate():
    # an ego on a circle turning 0.1 rad per 1 m step: poses exact, displacements chords
    yaw = 0.1 * torch.arange(-4.0, 7.0)
    radius = 1 / (2 * math.sin(0.05))
    xy = torch.stack([radius * torch.sin(yaw), radius * (1 - torch.cos(yaw))], -1)
    poses = torch.cat([xy, yaw[:, None]], -1)[None]
    past, future = poses[:, :5], poses[:, 5:]
    actions = past[:, 1:, :2] - past[:, :-1, :2]
    plan = constant_turn_rate(actions, 6)
    torch.testing.assert_close(planned_poses(plan, actions, past), future, atol=1e-4, rtol=0)
    # a plan turned 0.05 rad more than constant turn rate at every step turns its headings with it
    extra = torch.stack([torch.stack([a[0] * math.cos(0.05) - a[1] * math.sin(0.05),
                                      a[0] * math.sin(0.05) + a[1] * math.cos(0.05)]) for a in plan[0]])
    torch.testing.assert_close(planned_poses(extra[None], actions, past)[..., 2], future[..., 2] + 0.05)
    # a standing ego: a small correction does not swing its heading
    still = torch.zeros(1, 4, 2)
    nudge = torch.tensor([[[0.06, -0.08]] * 6])
    assert planned_poses(nudge, still, torch.zeros(1, 5, 3))[..., 2].abs().max() == 0
    # without past poses, the heading is the direction of travel
    torch.testing.assert_close(planned_poses(plan, actions), poses_from_displacements(plan))


def test_future_poses_give_their_displacements():
    model = aligned().eval()
    poses = torch.tensor([[[0.8, 0.0, 0.0], [1.6, 0.1, 0.1], [2.4, 0.3, 0.2]]])
    out = model.forecast(_past(), torch.eye(4).repeat(1, 5, 1, 1), future_actions=poses)
    assert torch.equal(out.poses, poses)
    torch.testing.assert_close(out.trajectory, poses[..., :2])
    torch.testing.assert_close(out.actions, torch.tensor([[[0.8, 0.0], [0.8, 0.1], [0.8, 0.2]]]))


@pytest.mark.parametrize(
    ("argument", "spoil", "message"),
    [
        ("past_motion", lambda m, f: m.__setitem__((0, 2, 1), float("nan")),
         r"past_motion must be finite, but past_motion\[0, 2, 1\] is nan"),
        ("past_motion", lambda m, f: m.__setitem__((0, 3, 0), float("inf")),
         r"past_motion\[0, 3, 0\] is inf"),
        ("future_actions", lambda m, f: f.__setitem__((0, 1, 0), float("-inf")),
         r"future_actions must be finite, but future_actions\[0, 1, 0\] is -inf"),
    ],
)
def test_forecast_refuses_non_finite_motion(argument, spoil, message):
    model = tiny_world_model().eval()
    motion, future = torch.full((1, 4, 2), 0.5), torch.full((1, 3, 2), 0.5)
    spoil(motion, future)
    with pytest.raises(UsageError, match=message):
        model.forecast(_past(), motion, future_actions=future if argument == "future_actions" else None)
    poses = torch.eye(4).repeat(1, 5, 1, 1)
    poses[0, 1, 0, 3] = float("nan")  # ego -> world poses too
    with pytest.raises(UsageError, match=r"past_motion\[0, 1, 0, 3\] is nan"):
        model.forecast(_past(), poses)


def test_forecast_refuses_a_history_the_model_was_not_trained_on():
    model = tiny_world_model().eval()
    assert model.forecaster.history == 5
    for frames in (3, 7):
        past = torch.stack([random_labels(1, (16, 12, 4), seed=s) for s in range(frames)], dim=1)
        with pytest.raises(UsageError, match=f"past_occupancy has {frames} past frames .* trained on 5"):
            model.forecast(past, torch.zeros(1, frames - 1, 2))
    with pytest.raises(UsageError, match=r"past_motion must be poses .* got shape \[1, 2, 2\]"):
        model.forecast(_past(), torch.zeros(1, 2, 2))  # 5 frames need 4 displacements
