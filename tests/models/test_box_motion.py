"""The learned motion of the fitted boxes: its inputs (the agent's view of the scene, its
kinematics), their mirror images, and the untrained network being the box tracker."""

from __future__ import annotations

import math

import torch

from t3fast.agents.box_kinematics import (
    CONTEXT_CHANNELS,
    CROP,
    CROP_BEHIND,
    CROP_CELL,
    STILL_STEP,
    VEHICLES,
    agent_headings,
    context_map,
    corrected_motion,
    crop_context,
    future_poses,
    kinematic_features,
    kinematics,
    mirror_kinematics,
    mirror_views,
)
from t3fast.agents.boxes import AgentBoxes
from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, PEDESTRIAN, SIDEWALK
from t3fast.models.box_motion import BoxMotionNet, predict_box_poses, symmetric_correction


def _boxes(track: torch.Tensor, velocity: torch.Tensor, yaw: torch.Tensor, labels: list[int]) -> AgentBoxes:
    n = track.shape[0]
    size = torch.ones(n, dtype=torch.float64)
    return AgentBoxes(centre=track[:, -1].clone(), velocity=velocity, yaw=yaw, length=4.5 * size, width=1.9 * size,
                      bottom=torch.ones(n, dtype=torch.long), top=torch.full((n,), 5, dtype=torch.long),
                      label=torch.tensor(labels), drawn=torch.ones(n, dtype=torch.bool), track=track)


def _braking_car_and_walker() -> AgentBoxes:
    """A car braking while it drives up and to the left, a pedestrian walking, one frame unseen."""
    t = torch.arange(-4, 1, dtype=torch.float64)
    car = torch.stack([3.0 + 1.2 * t - 0.05 * t**2, -2.0 + 0.4 * t], -1)
    walker = torch.stack([-6.0 - 0.3 * t, 5.0 + 0.6 * t], -1)
    walker[0] = math.nan
    track = torch.stack([car, walker])
    velocity = torch.tensor([[1.15, 0.4], [-0.3, 0.6]], dtype=torch.float64)
    return _boxes(track, velocity, torch.tensor([0.3, 2.0], dtype=torch.float64), [CAR, PEDESTRIAN])


def test_kinematics_are_read_in_the_agents_own_frame_and_mirror_exactly():
    boxes = _braking_car_and_walker()
    heading = agent_headings(boxes)
    assert torch.allclose(heading, torch.atan2(boxes.velocity[:, 1], boxes.velocity[:, 0]))
    features = kinematics(boxes, heading)
    assert features.shape == (2, kinematic_features(5))
    assert torch.allclose(features[:, 1], torch.zeros(2), atol=1e-6)  # all its velocity is along its heading
    assert torch.allclose(features[:, 0], boxes.velocity.norm(dim=-1).float())
    assert features[1, 11] == 0 and features[1, 12:15].eq(1).all()  # the walker's first frame was not seen
    # the same agents mirrored across the x axis: the features are mirror_kinematics of the originals
    mirrored = _boxes(boxes.track * torch.tensor([1.0, -1.0], dtype=torch.float64),
                      boxes.velocity * torch.tensor([1.0, -1.0], dtype=torch.float64), -boxes.yaw, [CAR, PEDESTRIAN])
    assert torch.allclose(kinematics(mirrored, agent_headings(mirrored)), mirror_kinematics(features), atol=1e-6)
    assert torch.equal(mirror_kinematics(mirror_kinematics(features)), features)


def test_a_still_agent_keeps_the_frame_of_its_box():
    boxes = _braking_car_and_walker()
    boxes.velocity[0] = 0.0
    assert agent_headings(boxes)[0] == boxes.yaw[0]


def test_the_view_shows_what_lies_ahead_and_turns_velocities_into_the_agents_frame():
    context = torch.zeros(CONTEXT_CHANNELS, 200, 200)
    # an agent at (10, 0) heading along +y; a block 6 m ahead of it (at x = 10, y = 6) moving along +y
    context[0, 124:126, 114:116] = 1  # cells of x in [9.6, 10.4), y in [5.6, 6.4)
    context[-2:, 124:126, 114:116] = torch.tensor([0.0, 2.0]).view(2, 1, 1)
    views = crop_context(context, torch.tensor([[10.0, 0.0]]), torch.tensor([math.pi / 2]))
    assert views.shape == (1, CONTEXT_CHANNELS, *CROP)
    row = int((6.0 + CROP_BEHIND) / CROP_CELL)
    col = (CROP[1] - 1) / 2  # its centre line lies between the two middle columns
    hot = views[0, 0].nonzero().float()
    assert abs(hot[:, 0].mean() - row + 0.5) < 1.0 and abs(hot[:, 1].mean() - col) < 1.0
    ahead = views[0, -2:, hot[:, 0].long(), hot[:, 1].long()]
    assert torch.allclose(ahead[0], views[0, 0, hot[:, 0].long(), hot[:, 1].long()] * 2, atol=1e-5)
    assert torch.allclose(ahead[1], torch.zeros_like(ahead[1]), atol=1e-5)  # nothing across its heading


def test_the_view_of_the_mirrored_world_is_the_mirrored_view():
    torch.manual_seed(0)
    context = torch.rand(CONTEXT_CHANNELS, 200, 200)
    mirrored = context.flip(-1)  # y -> -y about the grid's centre line
    mirrored[-1] = -mirrored[-1]
    centre, heading = torch.tensor([[7.3, 0.0]]), torch.tensor([0.0])
    assert torch.allclose(crop_context(mirrored, centre, heading), mirror_views(crop_context(context, centre, heading)),
                          atol=1e-5)
    views = crop_context(context, torch.tensor([[3.0, -2.0]]), torch.tensor([0.4]))
    assert torch.equal(mirror_views(mirror_views(views)), views)


def test_the_context_holds_the_ground_the_agents_and_the_ego():
    present = torch.full((200, 200, 16), FREE, dtype=torch.uint8)
    present[:100, :, 0] = DRIVEABLE_SURFACE
    present[100:, :, 0] = SIDEWALK
    present[150:155, 20:25, 1:4] = CAR
    ids = torch.zeros(200, 200, dtype=torch.long)
    ids[150:155, 20:25] = 1
    boxes = _boxes(torch.zeros(1, 5, 2, dtype=torch.float64), torch.tensor([[0.7, -0.2]], dtype=torch.float64),
                   torch.zeros(1, dtype=torch.float64), [CAR])
    context = context_map(present, boxes, ids, torch.tensor([1.5, 0.0]))
    assert context.shape == (CONTEXT_CHANNELS, 200, 200)
    assert context[0, :100].eq(1).all() and context[0, 100:].eq(0).all() and context[1, 100:].eq(1).all()
    assert context[VEHICLES, 150:155, 20:25].eq(1).all()
    assert torch.allclose(context[-2:, 152, 22], torch.tensor([0.7, -0.2]))
    # the ego: 4.1 m x 1.85 m at the origin, a vehicle with its last step's velocity
    assert context[VEHICLES, 100, 100] == 1 and torch.allclose(context[-2:, 100, 100], torch.tensor([1.5, 0.0]))
    assert context[VEHICLES, 100, 102] == 0 and context[VEHICLES, 104, 100] == 1 and context[VEHICLES, 105, 100] == 0


def test_the_untrained_network_moves_boxes_at_their_fitted_velocity():
    boxes = _braking_car_and_walker()
    net = BoxMotionNet()
    present = torch.full((200, 200, 16), FREE, dtype=torch.uint8)
    poses = predict_box_poses(net, present, boxes, torch.zeros(200, 200, dtype=torch.long), torch.zeros(2))
    k = torch.arange(1, 7, dtype=torch.float64)[:, None, None]
    assert poses.shape == (6, 2, 3)
    assert torch.allclose(poses[..., :2], boxes.centre[None] + k * boxes.velocity[None], atol=1e-5)
    assert torch.allclose(poses[..., 2], boxes.yaw.expand(6, 2))
    # a correction is a displacement along and across the heading, and a yaw change
    correction = torch.zeros(2, 6, 3)
    correction[0, :, 0], correction[1, :, 1], correction[1, :, 2] = 1.0, 2.0, 0.1
    displacement, turn = corrected_motion(boxes.velocity, agent_headings(boxes), correction.double())
    heading = agent_headings(boxes)
    along = torch.stack([heading.cos(), heading.sin()], -1)
    left = torch.stack([-heading.sin(), heading.cos()], -1)
    assert torch.allclose(displacement[0] - k[:, 0] * boxes.velocity[0], along[0].expand(6, 2), atol=1e-6)
    assert torch.allclose(displacement[1] - k[:, 0] * boxes.velocity[1], 2 * left[1].expand(6, 2), atol=1e-6)
    assert torch.allclose(future_poses(boxes, heading, correction)[:, 1, 2], boxes.yaw[1] + turn[1])
    empty = _boxes(torch.zeros(0, 5, 2, dtype=torch.float64), torch.zeros(0, 2, dtype=torch.float64),
                   torch.zeros(0, dtype=torch.float64), [])
    assert predict_box_poses(net, present, empty, torch.zeros(200, 200, dtype=torch.long),
                             torch.zeros(2)).shape == (6, 0, 3)


def test_a_standing_agent_keeps_its_present_pose_whatever_the_network_says():
    boxes = _braking_car_and_walker()
    boxes.velocity[1] = torch.tensor([0.1, -0.1], dtype=torch.float64)  # 0.14 m/step: the fit's noise
    correction = torch.zeros(2, 6, 3, dtype=torch.float64)
    correction[..., 0], correction[..., 2] = 0.5, 0.2
    heading = agent_headings(boxes)
    poses = future_poses(boxes, heading, correction)
    present = torch.cat([boxes.centre[1], boxes.yaw[1:]])
    assert torch.equal(poses[:, 1], present.expand(6, 3))
    displacement, turn = corrected_motion(boxes.velocity, heading, correction)
    assert torch.allclose(poses[:, 0, :2], boxes.centre[0] + displacement[0])  # the car drives on
    assert torch.allclose(poses[:, 0, 2], boxes.yaw[0] + turn[0])
    boxes.velocity[1] = torch.tensor([STILL_STEP, 0.0], dtype=torch.float64)  # as fast: it walks
    assert not torch.equal(future_poses(boxes, heading, correction)[:, 1], present.expand(6, 3))


def test_the_symmetric_correction_of_a_mirrored_agent_is_the_mirrored_correction():
    torch.manual_seed(0)
    net = BoxMotionNet()
    torch.nn.init.normal_(net.head[-1].weight, std=0.1)  # a trained-like head: not symmetric by itself
    views = torch.rand(3, CONTEXT_CHANNELS, *CROP)
    features = torch.randn(3, kinematic_features(5))
    flip = torch.tensor([1.0, -1.0, -1.0])
    got = symmetric_correction(net, mirror_views(views), mirror_kinematics(features))
    assert torch.allclose(got, symmetric_correction(net, views, features) * flip, atol=1e-6)
    one_pass = net(mirror_views(views), mirror_kinematics(features))
    assert not torch.allclose(one_pass, net(views, features) * flip, atol=1e-3)


def test_the_network_reads_both_the_view_and_the_kinematics():
    torch.manual_seed(0)
    net = BoxMotionNet()
    torch.nn.init.normal_(net.head[-1].weight, std=0.1)
    views, features = torch.rand(3, CONTEXT_CHANNELS, *CROP), torch.rand(3, kinematic_features(5))
    out = net(views, features)
    assert out.shape == (3, 6, 3)
    assert not torch.allclose(net(views * 0, features), out) and not torch.allclose(net(views, features * 0), out)
