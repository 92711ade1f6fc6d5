"""Flow targets from the agents' boxes."""

from __future__ import annotations

import math

import torch

from t3fast.data.sample import PRESENT, WINDOW
from t3fast.training.world_model.motion_targets import agent_flow, plane_cell_centres


def _boxes(speed: float, yaw: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """One car 4 m x 2 m at (0.4, 0.4) m in the present frame, moving ``speed`` m per frame along x."""
    boxes = torch.zeros(1, WINDOW, 1, 7)
    for t in range(WINDOW):
        boxes[0, t, 0] = torch.tensor([0.4 + speed * (t - PRESENT), 0.4, 0.0, 4.0, 2.0, 1.5, yaw])
    return boxes, torch.ones(1, WINDOW, 1, dtype=torch.bool)


def test_cell_centres_are_symmetric_plane_cells():
    centres = plane_cell_centres((100, 100), torch.device("cpu"))
    assert torch.allclose(centres[0, 0], torch.tensor([-39.6, -39.6]))
    assert torch.allclose(centres[50, 49], torch.tensor([0.4, -0.4]))


def test_a_car_moving_along_x_gives_its_cells_the_motion_back():
    boxes, valid = _boxes(speed=1.6)  # two plane cells per step
    flow, moving, static = agent_flow(boxes, valid)
    assert flow.shape == (1, 6, 2, 100, 100) and moving.shape == static.shape == (1, 6, 100, 100)
    for k in range(6):
        cells = moving[0, k]
        assert cells.any()
        assert torch.allclose(flow[0, k, 0][cells], torch.tensor(-2.0 * (k + 1)), atol=1e-4)
        assert torch.allclose(flow[0, k, 1][cells], torch.tensor(0.0), atol=1e-4)
        assert (flow[0, k][:, ~cells] == 0).all()
    # the car's cells at step 1 (2 frames on): centres x in [3.6 - 2 - 0.4, 3.6 + 2 + 0.4] = cells 51..57
    rows = moving[0, 1].any(1).nonzero().squeeze(1)
    assert rows.min() == 51 and rows.max() == 57
    # what it leaves behind is neither moving nor static (new content: no flow target)
    assert not moving[0, 5, 50, 50] and not static[0, 5, 50, 50]
    assert static[0, 0, 10, 10] and not static[0, 0, 53, 50]


def test_a_turned_box_maps_its_points_rigidly():
    boxes, valid = _boxes(speed=0.0)
    boxes[0, PRESENT + 1 :, 0, 6] = math.pi / 2  # the car turns in place by 90 degrees
    flow, moving, _ = agent_flow(boxes, valid)
    centres = plane_cell_centres((100, 100), torch.device("cpu"))
    cells = moving[0, 0]
    src = centres[cells] + flow[0, 0].permute(1, 2, 0)[cells] * 0.8
    rel, rel_src = centres[cells] - 0.4, src - 0.4
    assert torch.allclose(rel_src, torch.stack([rel[:, 1], -rel[:, 0]], dim=1), atol=1e-4)  # rotated back by -90


def test_agents_out_of_view_now_have_no_flow_target():
    boxes, valid = _boxes(speed=1.6)
    valid[0, PRESENT] = False
    flow, moving, _ = agent_flow(boxes, valid)
    assert not moving.any() and (flow == 0).all()


def test_a_parked_car_is_static_not_moving():
    boxes, valid = _boxes(speed=0.0)
    flow, moving, static = agent_flow(boxes, valid)
    assert not moving.any() and (flow.abs() < 1e-4).all()
    assert static[0, :, 50, 50].all()  # its cells keep their content: flow target 0
