"""The flow forecaster's stage-2 loss: where the displacement is supervised, and where it is not."""

from __future__ import annotations

import torch
from torch import nn

from t3fast.data.sample import PRESENT, WINDOW
from t3fast.models.triplane import Triplane
from t3fast.training.configs import WorldLossConfig
from t3fast.training.world_model.latent_cache import AlignedBatch
from t3fast.training.world_model.motion_loss import motion_loss


class _Fixed(nn.Module):
    """A forecaster that copies the present plane and moves every cell by a given displacement."""

    def __init__(self, displacement: torch.Tensor):
        super().__init__()
        self.displacement = displacement

    def forward(self, past, velocity, plan_from):
        futures = [past.map(lambda p: p[:, -1]) for _ in range(6)]
        return futures, self.displacement, None, None


def _batch() -> AlignedBatch:
    """A car moving 1.6 m (2 plane cells) a frame along x at the origin, a parked one at (20, 0) m;
    the tracker measured both, and the ring of cells around each. The boxes' edges (0.4 m
    margin) fall between cell centres: the moving car covers rows 47-52, columns 48-51."""
    boxes = torch.zeros(1, WINDOW, 2, 7)
    for t in range(WINDOW):
        boxes[0, t, 0] = torch.tensor([1.6 * (t - PRESENT), 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
        boxes[0, t, 1] = torch.tensor([20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    velocity = torch.zeros(1, 4, 100, 100)
    velocity[0, 0, 46:54, 47:53] = 2.0  # the moving car with its ring
    velocity[0, 0, 71:80, 47:53] = 0.5  # the parked car drifts in the tracker's eyes
    planes = Triplane(torch.zeros(1, WINDOW, 2, 100, 100), None, None)
    return AlignedBatch(planes, boxes, torch.ones(1, WINDOW, 2, dtype=torch.bool), torch.zeros(1, 4, 2),
                        torch.zeros(1, 6, 2), velocity)


def _loss(displacement: torch.Tensor) -> tuple[float, dict[str, float]]:
    cfg = WorldLossConfig(flow_weight=1.0, static_flow_weight=0.2)
    total, parts = motion_loss(_Fixed(displacement), _batch(), cfg)
    return float(total), parts


def _tracker_motion() -> torch.Tensor:
    velocity = _batch().velocity[:, :2]
    return torch.stack([(k + 1) * velocity for k in range(6)], 1)


def test_the_true_motion_scores_zero_on_moving_and_parked_agents():
    truth = torch.zeros(1, 6, 2, 100, 100)
    for k in range(6):
        truth[0, k, 0, 47:53, 48:52] = 2.0 * (k + 1)
    total, parts = _loss(truth)
    assert parts["flow_moving"] < 1e-3 and parts["flow_parked"] == 0 and parts["flow_static"] == 0
    assert abs(total - parts["latent"]) < 1e-3


def test_a_parked_agents_drift_is_an_error_and_its_ring_has_no_target():
    drift = _tracker_motion()
    _, parts = _loss(drift)
    assert parts["flow_parked"] > 1.0  # the tracker's drift of the parked car is penalised
    # the tracked ring around the agents is neither moving nor static: any motion there is free
    ring = drift.clone()
    ring[0, :, :, 46, 47:53] = 50.0
    ring[0, :, :, 71, 47:53] = -50.0
    assert _loss(ring)[0] == _loss(drift)[0]
    # but the untracked world must stand still
    elsewhere = drift.clone()
    elsewhere[0, :, :, 10:20, 10:20] = 1.0
    assert _loss(elsewhere)[1]["flow_static"] > 0 and _loss(elsewhere)[0] > _loss(drift)[0]


def test_the_flow_term_is_each_agents_mean_motion_as_the_render_moves_it():
    """The render moves an agent by the mean displacement over its cells: a field right on
    average but uneven scores zero, one off on average by 1 cell scores 1 per axis wrong."""
    truth = torch.zeros(1, 6, 2, 100, 100)
    for k in range(6):
        truth[0, k, 0, 47:53, 48:52] = 2.0 * (k + 1)
    uneven = truth.clone()
    uneven[0, :, 0, 47:50, 48:52] += 1.0
    uneven[0, :, 0, 50:53, 48:52] -= 1.0
    assert _loss(uneven)[1]["flow_moving"] < 1e-4
    off = truth.clone()
    off[0, :, 1, 47:53, 48:52] += 1.0
    assert abs(_loss(off)[1]["flow_moving"] - 1.0) < 1e-4
