"""Planning metrics on hand-made trajectories and boxes."""

from __future__ import annotations

import math

import pytest
import torch

from t3fast.data.classes import CAR, DRIVEABLE_SURFACE
from t3fast.evaluation.planning import PlanningMetrics, cells_in_boxes, collisions, ego_boxes

STRAIGHT = torch.tensor([[2.0 * k, 0.0] for k in range(1, 7)])  # 2 m per step along x


def test_l2_at_and_mean_by_hand():
    planned = STRAIGHT.clone()
    planned[:, 1] = torch.arange(1, 7, dtype=torch.float32)  # drifts 1 m sideways per step
    metrics = PlanningMetrics()
    no_boxes = torch.zeros(1, 6, 0, 7)
    metrics.update(planned[None], STRAIGHT[None], no_boxes, torch.zeros(1, 6, 0, dtype=torch.bool),
                   torch.zeros(1, 0, dtype=torch.long))
    s = metrics.summary()
    assert s["l2_at"]["1s"] == pytest.approx(2.0) and s["l2_at"]["3s"] == pytest.approx(6.0)
    assert s["l2_mean"]["1s"] == pytest.approx(1.5)  # (1 + 2) / 2
    assert s["l2_mean"]["3s"] == pytest.approx(3.5)  # (1 + ... + 6) / 6
    assert s["l2_at"]["avg"] == pytest.approx(4.0)
    assert s["collision"]["3s"] == 0.0


def test_ego_heading_follows_motion():
    boxes = ego_boxes(torch.tensor([[0.0, 1.0], [0.0, 1.0], [1.0, 2.0]]))
    assert boxes[0, 6] == pytest.approx(math.pi / 2)
    assert boxes[1, 6] == pytest.approx(math.pi / 2)  # standing still keeps the heading
    assert boxes[2, 6] == pytest.approx(math.pi / 4)


def test_cells_in_rotated_box():
    cells = torch.tensor([[1.9, 0.0], [0.0, 0.9], [0.0, 1.1], [1.5, 1.5]])
    box = torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]])
    assert cells_in_boxes(cells, box)[0].tolist() == [True, True, False, False]
    turned = box.clone()
    turned[0, 6] = math.pi / 2  # now 2 m along x, 4 m along y
    assert cells_in_boxes(cells, turned)[0].tolist() == [False, True, True, False]


def test_collisions_only_with_agents_on_the_path():
    car = torch.tensor([8.0, 0.0, 0.0, 2.0, 1.9, 1.6, 0.0])  # covers x = 7..9 m
    boxes = car.expand(6, 1, 7).clone()
    valid = torch.ones(6, 1, dtype=torch.bool)
    hits = collisions(STRAIGHT, boxes, valid, torch.tensor([CAR]))
    # the ego (4.084 m long) is centred at x = 2, 4, ..., 12 m
    assert hits.tolist() == [False, False, True, True, True, False]
    # a static class (road) never counts
    assert not collisions(STRAIGHT, boxes, valid, torch.tensor([DRIVEABLE_SURFACE])).any()
    assert not collisions(STRAIGHT, boxes, ~valid, torch.tensor([CAR])).any()


def test_steps_where_the_truth_collides_are_excluded():
    car = torch.tensor([8.0, 0.0, 0.0, 2.0, 1.9, 1.6, 0.0]).expand(1, 6, 1, 7).clone()
    valid, labels = torch.ones(1, 6, 1, dtype=torch.bool), torch.tensor([[CAR]])
    swerve = STRAIGHT.clone()
    swerve[:, 1] = 5.0  # 5 m to the side: never collides
    metrics = PlanningMetrics()
    metrics.update(STRAIGHT[None], swerve[None], car, valid, labels)  # planned hits at steps 3-5
    metrics.update(STRAIGHT[None], STRAIGHT[None], car, valid, labels)  # truth hits there too: excluded
    s = metrics.summary()
    assert s["collision"]["1s"] == 0.0
    assert s["collision"]["2s"] == pytest.approx(2 / 6)  # steps 1-4: 4 + 2 counted, 2 hits
    assert s["collision"]["3s"] == pytest.approx(3 / 9)  # steps 1-6: 6 + 3 counted, 3 hits


def test_rejects_mismatched_trajectories():
    with pytest.raises(ValueError, match=r"planned and truth must both be \[B, S, 2\]"):
        PlanningMetrics().update(torch.zeros(1, 6, 2), torch.zeros(1, 5, 2), torch.zeros(1, 6, 0, 7),
                                 torch.zeros(1, 6, 0, dtype=torch.bool), torch.zeros(1, 0, dtype=torch.long))
