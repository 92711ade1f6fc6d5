"""Forward displacement targets of the present cells from the agents' boxes."""

from __future__ import annotations

import math

import torch

from t3fast.data.sample import PRESENT, WINDOW
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.training.world_model.motion_targets import agent_motion, plane_cell_centres

CELL = 0.8  # metres per xy-plane cell of a 100 x 100 plane
# margin 0.3 keeps every box edge of these tests between cell centres (with the default 0.4 the
# edges of a box centred at 0.4 m fall exactly on cell centres: a float rounding decides them)
MARGIN = 0.3


def _boxes(speed: float, yaw: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """One car 4 m x 2 m at (0.4, 0.4) m in the present frame, moving ``speed`` m per frame along x."""
    boxes = torch.zeros(1, WINDOW, 1, 7)
    for t in range(WINDOW):
        boxes[0, t, 0] = torch.tensor([0.4 + speed * (t - PRESENT), 0.4, 0.0, 4.0, 2.0, 1.5, yaw])
    return boxes, torch.ones(1, WINDOW, 1, dtype=torch.bool)


def _rect(rows: range, cols: range) -> torch.Tensor:
    mask = torch.zeros(100, 100, dtype=torch.bool)
    mask[rows.start : rows.stop, cols.start : cols.stop] = True
    return mask


# the present car: x in [0.4 - 2.3, 0.4 + 2.3] -> cell centres -39.6 + 0.8 i for i = 48..52;
# y in [0.4 - 1.3, 0.4 + 1.3] -> j = 49..51
PRESENT_CAR = _rect(range(48, 53), range(49, 52))


def test_cell_centres_are_symmetric_plane_cells():
    centres = plane_cell_centres((100, 100), torch.device("cpu"))
    assert centres.shape == (100, 100, 2)
    assert torch.allclose(centres[0, 0], torch.tensor([-39.6, -39.6]))
    assert torch.allclose(centres[50, 49], torch.tensor([0.4, -0.4]))
    assert torch.allclose(centres.flip(0, 1), -centres, atol=1e-5)


def test_a_car_moving_along_x_gives_its_present_cells_their_forward_motion():
    boxes, valid = _boxes(speed=1.6)  # two plane cells per frame
    disp, moving, static, agents, covered, owner = agent_motion(boxes, valid, margin=MARGIN)
    assert disp.shape == (1, 6, 2, 100, 100)
    assert covered.shape == (1, 100, 100) and torch.equal(covered[0], PRESENT_CAR)
    assert torch.equal(owner[0], torch.where(PRESENT_CAR, 0, -1))  # box 0 covers the car's cells
    assert moving.shape == static.shape == agents.shape == (1, 6, 100, 100)
    assert moving.dtype == static.dtype == agents.dtype == torch.bool
    for k in range(6):
        # the moving cells are those of the box now, whatever the step
        assert torch.equal(moving[0, k], PRESENT_CAR)
        assert torch.allclose(disp[0, k, 0][PRESENT_CAR], torch.tensor(2.0 * (k + 1)), atol=1e-4)
        assert torch.allclose(disp[0, k, 1][PRESENT_CAR], torch.tensor(0.0), atol=1e-4)
        assert (disp[0, k][:, ~PRESENT_CAR] == 0).all()
        # cells outside the present box are static, those where the car will be included
        assert torch.equal(static[0, k], ~PRESENT_CAR)
    # the last step's box: centre x = 0.4 + 1.6 * 6 = 10.0 -> [7.7, 12.3] -> rows 60..64
    assert torch.equal(agents[0, 5], PRESENT_CAR | _rect(range(60, 65), range(49, 52)))
    # the first step's box (centre x 2.0 -> [-0.3, 4.3] -> rows 50..54) overlaps the present one
    assert torch.equal(agents[0, 0], _rect(range(48, 55), range(49, 52)))
    assert static[0, 5, 62, 50] and agents[0, 5, 62, 50] and not moving[0, 5, 62, 50]


def test_two_agents_and_a_batch_keep_their_own_motion():
    boxes = torch.zeros(2, WINDOW, 3, 7)
    valid = torch.zeros(2, WINDOW, 3, dtype=torch.bool)
    car, _ = _boxes(speed=1.6)
    boxes[0, :, 0] = car[0, :, 0]
    for t in range(WINDOW):  # agent 1: a 2.4 m x 1.6 m box at (-20.4, 15.6) moving 0.8 m/frame along -y
        boxes[0, t, 1] = torch.tensor([-20.4, 15.6 - 0.8 * (t - PRESENT), 0.0, 2.4, 1.6, 1.5, 0.0])
    boxes[1, :, 0] = torch.tensor([0.4, 0.4, 0.0, 4.0, 2.0, 1.5, 0.0])  # window 1: parked
    valid[0, :, :2] = True
    valid[1, :, 0] = True
    boxes[:, :, 2] = 7.0  # an invalid padding box: ignored whatever it holds
    disp, moving, static, _, _, _ = agent_motion(boxes, valid, margin=MARGIN)
    # agent 1: x in [-21.9, -18.9] -> rows 23..25 ; y in [14.5, 16.7] -> cols 68..70
    second = _rect(range(23, 26), range(68, 71))
    for k in range(6):
        assert torch.equal(moving[0, k], PRESENT_CAR | second)
        assert torch.allclose(disp[0, k, 0][second], torch.tensor(0.0), atol=1e-4)
        assert torch.allclose(disp[0, k, 1][second], torch.tensor(-(k + 1.0)), atol=1e-4)
        assert torch.allclose(disp[0, k, 0][PRESENT_CAR], torch.tensor(2.0 * (k + 1)), atol=1e-4)
    assert not moving[1].any() and static[1].all() and (disp[1].abs() < 1e-4).all()


def test_a_turning_box_maps_its_points_rigidly():
    boxes, valid = _boxes(speed=0.0, yaw=0.3)
    for k in range(6):  # it drives diagonally and turns 0.4 rad per frame
        boxes[0, PRESENT + 1 + k, 0, :2] = torch.tensor([0.4 + 0.5 * (k + 1), 0.4 - 0.3 * (k + 1)])
        boxes[0, PRESENT + 1 + k, 0, 6] = 0.3 + 0.4 * (k + 1)
    disp, moving, static, _, _, _ = agent_motion(boxes, valid, margin=MARGIN)
    centres = plane_cell_centres((100, 100), torch.device("cpu")).double()
    c0 = torch.tensor([0.4, 0.4], dtype=torch.float64)

    def rotate(v: torch.Tensor, angle: float) -> torch.Tensor:
        c, s = math.cos(angle), math.sin(angle)
        return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], dim=-1)

    local = rotate(centres - c0, -0.3)
    box = (local.abs() <= torch.tensor([2.0 + MARGIN, 1.0 + MARGIN], dtype=torch.float64)).all(-1)
    assert box.sum() > 20
    for k in range(6):
        ck = torch.tensor([0.4 + 0.5 * (k + 1), 0.4 - 0.3 * (k + 1)], dtype=torch.float64)
        expected = ck + rotate(centres - c0, 0.4 * (k + 1))  # where each point of the car goes
        target = centres + disp[0, k].permute(1, 2, 0).double() * CELL
        assert torch.allclose(target[box], expected[box], atol=1e-4)
        assert (disp[0, k][:, ~box] == 0).all()
        size = disp[0, k].norm(dim=0)
        assert torch.equal(moving[0, k], box & (size >= 0.5))
        assert torch.equal(static[0, k], ~box | (size < 0.5))
    # an in-place turn by 90 degrees: a point 1 m ahead of the centre goes 1 m to its left
    boxes, valid = _boxes(speed=0.0)
    boxes[0, PRESENT + 1 :, 0, 6] = math.pi / 2
    disp, moving, _, _, _, _ = agent_motion(boxes, valid, margin=MARGIN)
    # cell (51, 50) has its centre at (1.2, 0.4): 0.8 m ahead of the car's centre -> (0.4, 1.2)
    assert torch.allclose(disp[0, 0, :, 51, 50], torch.tensor([-1.0, 1.0]), atol=1e-4)
    assert moving[0, 0, 51, 50] and not moving[0, 0, 50, 50]  # the centre turns in place


def test_an_agent_invalid_now_has_no_target():
    boxes, valid = _boxes(speed=1.6)
    valid[0, PRESENT] = False
    disp, moving, static, agents, _, _ = agent_motion(boxes, valid, margin=MARGIN)
    assert not moving.any() and (disp == 0).all()
    assert static.all()  # no box covers any cell now: the world stands still
    # but where it is at each step is still an agent's place: rows 60..64 at the last step
    assert torch.equal(agents[0, 5], _rect(range(60, 65), range(49, 52)))


def test_an_agent_invalid_at_a_future_frame_has_no_target_at_that_frame():
    boxes, valid = _boxes(speed=1.6)
    valid[0, PRESENT + 3] = False  # step 2
    disp, moving, static, agents, _, _ = agent_motion(boxes, valid, margin=MARGIN)
    assert not moving[0, 2].any() and (disp[0, 2] == 0).all()
    assert not static[0, 2][PRESENT_CAR].any()  # neither moving nor static: no target
    assert static[0, 2][~PRESENT_CAR].all()
    assert torch.equal(agents[0, 2], PRESENT_CAR)  # its box then is unknown
    for k in (0, 1, 3, 4, 5):
        assert torch.equal(moving[0, k], PRESENT_CAR)
        assert torch.allclose(disp[0, k, 0][PRESENT_CAR], torch.tensor(2.0 * (k + 1)), atol=1e-4)


def test_a_parked_car_is_static_not_moving():
    boxes, valid = _boxes(speed=0.0)
    disp, moving, static, agents, _, _ = agent_motion(boxes, valid, margin=MARGIN)
    assert not moving.any() and (disp.abs() < 1e-4).all()
    assert static.all()  # its cells keep their content: displacement target 0
    assert all(torch.equal(agents[0, k], PRESENT_CAR) for k in range(6))


def test_min_flow_decides_what_moves():
    boxes, valid = _boxes(speed=0.32)  # 0.4 cells per frame: 0.4 (k + 1) cells at step k
    _, moving, static, _, _, _ = agent_motion(boxes, valid, margin=MARGIN, min_flow=1.0)
    # steps 0 and 1 (0.4 and 0.8 cells) are under 1 cell: static; from step 2 (1.2 cells) moving
    assert not moving[0, :2].any() and static[0, :2].all()
    assert all(torch.equal(moving[0, k], PRESENT_CAR) for k in range(2, 6))


def test_the_targets_are_made_without_a_host_read_or_host_data():
    """As in a training step on a GPU: nothing waits for the device, nothing is copied to it."""
    boxes, valid = _boxes(speed=1.6)
    agent_motion(boxes, valid, margin=MARGIN)  # the device constants made once
    with sync_free(), SyncCounter() as counter:
        agent_motion(boxes, valid, margin=MARGIN)
    assert counter.total == 0 and not counter.host_data, (counter.by_caller, counter.host_data)
