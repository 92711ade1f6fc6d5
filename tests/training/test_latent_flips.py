"""Mirrored and transposed cached windows: exact rearrangements of planes, boxes and actions."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from t3fast.agents.tracker import tracker_velocities
from t3fast.data.classes import CAR, FREE, PEDESTRIAN
from t3fast.data.route import route_command
from t3fast.data.sample import PRESENT, WINDOW
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.models.triplane import Triplane
from t3fast.training.world_model import latent_flips
from t3fast.training.world_model.latent_cache import AlignedBatch
from t3fast.training.world_model.latent_flips import flip_aligned, random_flips
from t3fast.training.world_model.motion_targets import agent_motion

ALL_FLIPS = list(itertools.product((False, True), repeat=3))


def _track(start: tuple[float, float], velocity: tuple[float, float], size: tuple[float, float], yaw: float,
           turn: float = 0.0) -> torch.Tensor:
    """``[WINDOW, 7]`` boxes of an agent at ``start`` in the present frame, moving ``velocity`` m and
    turning ``turn`` rad per frame."""
    t = torch.arange(WINDOW, dtype=torch.float32) - PRESENT
    return torch.stack([start[0] + velocity[0] * t, start[1] + velocity[1] * t, torch.full_like(t, 0.2),
                        torch.full_like(t, size[0]), torch.full_like(t, size[1]), torch.full_like(t, 1.5),
                        yaw + turn * t], dim=-1)


def _batch(h: int = 6, w: int = 6, z: int = 3, c: int = 2, bev: bool = False) -> AlignedBatch:
    torch.manual_seed(0)
    boxes = torch.zeros(2, WINDOW, 3, 7)
    valid = torch.zeros(2, WINDOW, 3, dtype=torch.bool)
    # window 0: a car off every axis of symmetry driving diagonally and turning, and a second one
    # that is not seen at one future frame; agent 2 is padding (invalid, zero)
    boxes[0, :, 0] = _track((5.3, -7.1), (1.1, 0.7), (4.4, 1.9), 0.6, turn=0.05)
    boxes[0, :, 1] = _track((-12.2, 9.7), (-0.3, 0.9), (3.9, 1.8), -2.2)
    valid[0, :, :2] = True
    valid[0, PRESENT + 2, 1] = False
    boxes[0, PRESENT + 2, 1] = 0.0
    # window 1: a parked car and one that is not seen now (it enters the view)
    boxes[1, :, 0] = _track((20.1, 3.3), (0.0, 0.0), (4.6, 2.0), 2.9)
    boxes[1, :, 1] = _track((-5.5, -15.3), (0.6, -1.3), (4.1, 1.7), -1.1)
    valid[1, :, :2] = True
    valid[1, : PRESENT + 1, 1] = False
    boxes[1, : PRESENT + 1, 1] = 0.0
    planes = Triplane(torch.randn(2, WINDOW, c, h, w), None if bev else torch.randn(2, WINDOW, c, h, z),
                      None if bev else torch.randn(2, WINDOW, c, w, z))
    return AlignedBatch(planes, boxes, valid, torch.randn(2, 4, 2), torch.randn(2, 6, 2), torch.randn(2, 4, h, w))


def _wrapped(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


def _assert_same_batch(a: AlignedBatch, b: AlignedBatch) -> None:
    for p, q in zip(a.planes, b.planes):
        assert (p is None and q is None) or torch.equal(p, q)
    assert torch.equal(a.box_valid, b.box_valid)
    assert torch.equal(a.past_actions, b.past_actions) and torch.equal(a.future_actions, b.future_actions)
    assert torch.equal(a.velocity, b.velocity)
    v = a.box_valid
    assert torch.allclose(a.boxes[v][:, :6], b.boxes[v][:, :6], atol=1e-5)
    assert torch.allclose(_wrapped(a.boxes[v][:, 6] - b.boxes[v][:, 6]), torch.tensor(0.0), atol=1e-5)
    assert (b.boxes[~v] == 0).all()


@pytest.mark.parametrize("flips", [(True, False, False), (False, True, False), (False, False, True),
                                   (True, True, False), (True, True, True)])
def test_a_flip_applied_twice_is_the_identity(flips):
    batch = _batch()
    once = flip_aligned(batch, *flips)
    assert not torch.equal(once.planes.xy, batch.planes.xy)  # it did change something
    _assert_same_batch(batch, flip_aligned(once, *flips))


def test_a_mirror_and_a_transposition_make_a_quarter_turn():
    batch = _batch()
    quarter = lambda b: flip_aligned(b, True, False, True)  # noqa: E731
    half = quarter(quarter(batch))
    _assert_same_batch(flip_aligned(batch, True, True, False), half)  # two quarter turns: x, y -> -x, -y
    _assert_same_batch(batch, quarter(quarter(half)))


def test_each_flip_rearranges_planes_boxes_and_actions():
    batch = _batch()
    xy, xz, yz = batch.planes
    box = batch.boxes[0, PRESENT, 0]  # (5.3, -7.1), yaw 0.6
    out = flip_aligned(batch, True, False, False)
    assert torch.equal(out.planes.xy, xy.flip(-2)) and torch.equal(out.planes.xz, xz.flip(-2))
    assert torch.equal(out.planes.yz, yz)
    assert torch.allclose(out.boxes[0, PRESENT, 0], torch.tensor([-5.3, -7.1, 0.2, 4.4, 1.9, 1.5, math.pi - 0.6]))
    assert torch.equal(out.past_actions[..., 0], -batch.past_actions[..., 0])
    assert torch.equal(out.future_actions[..., 1], batch.future_actions[..., 1])
    out = flip_aligned(batch, False, True, False)
    assert torch.equal(out.planes.xy, xy.flip(-1)) and torch.equal(out.planes.yz, yz.flip(-2))
    assert torch.equal(out.planes.xz, xz)
    assert torch.allclose(out.boxes[0, PRESENT, 0], torch.tensor([5.3, 7.1, 0.2, 4.4, 1.9, 1.5, -0.6]))
    assert torch.equal(out.future_actions[..., 1], -batch.future_actions[..., 1])
    assert torch.equal(out.past_actions[..., 0], batch.past_actions[..., 0])
    out = flip_aligned(batch, False, False, True)
    assert torch.equal(out.planes.xy, xy.transpose(-2, -1))
    assert torch.equal(out.planes.xz, yz) and torch.equal(out.planes.yz, xz)  # the height profiles swap
    assert torch.allclose(out.boxes[0, PRESENT, 0], torch.tensor([-7.1, 5.3, 0.2, 4.4, 1.9, 1.5, math.pi / 2 - 0.6]))
    assert torch.equal(out.past_actions, batch.past_actions.flip(-1))
    assert torch.equal(out.future_actions, batch.future_actions.flip(-1))
    # yaw stays in [-pi, pi): mirroring x turns the second car's -2.2 into pi + 2.2 - 2 pi
    mirrored = flip_aligned(batch, True, False, False).boxes[0, PRESENT, 1, 6]
    assert torch.allclose(mirrored, torch.tensor(2.2 - math.pi))
    assert torch.equal(box, torch.tensor([5.3, -7.1, 0.2, 4.4, 1.9, 1.5, 0.6]))  # the input is left as it was


@pytest.mark.parametrize("flips", ALL_FLIPS)
def test_motion_targets_of_a_flipped_window_are_the_flipped_targets(flips):
    flip_x, flip_y, transpose = flips
    batch = _batch()
    disp, *masks = agent_motion(batch.boxes, batch.box_valid)
    assert masks[0][0].any() and masks[0][1].sum() == 0  # window 0 moves; window 1 is parked or unseen now
    if flip_x:
        disp, masks = disp.flip(-2) * torch.tensor([-1.0, 1.0]).view(2, 1, 1), [m.flip(-2) for m in masks]
    if flip_y:
        disp, masks = disp.flip(-1) * torch.tensor([1.0, -1.0]).view(2, 1, 1), [m.flip(-1) for m in masks]
    if transpose:
        disp, masks = disp.transpose(-2, -1)[:, :, [1, 0]], [m.transpose(-2, -1) for m in masks]
    out = flip_aligned(batch, flip_x, flip_y, transpose)
    flipped_disp, *flipped_masks = agent_motion(out.boxes, out.box_valid)
    assert torch.allclose(flipped_disp, disp, atol=1e-4)
    for got, expected in zip(flipped_masks, masks):  # moving, static, agents
        assert torch.equal(got, expected)


@pytest.mark.parametrize("flips", ALL_FLIPS)
def test_velocities_of_a_flipped_window_are_the_flipped_velocities(flips):
    """The tracker prior measured on mirrored/transposed frames is the flipped prior."""
    flip_x, flip_y, transpose = flips
    frames = torch.full((1, 3, 20, 20, 4), FREE, dtype=torch.uint8)
    for t, (x, y) in enumerate([(1, 12), (3, 11), (7, 9)]):  # a car speeding up, off every symmetry axis
        frames[0, t, x : x + 4, y : y + 2, :2] = CAR
    frames[0, :, 14:16, 2:4, 0] = PEDESTRIAN  # a standing pedestrian
    velocity = tracker_velocities(frames, (10, 10))
    assert velocity[:, :2].abs().sum() > 0 and not torch.equal(velocity[:, :2], velocity[:, 2:])
    batch = _batch(h=10, w=10)
    batch = AlignedBatch(batch.planes, batch.boxes, batch.box_valid, batch.past_actions, batch.future_actions,
                         velocity.expand(2, -1, -1, -1))
    if flip_x:
        frames = frames.flip(-3)
    if flip_y:
        frames = frames.flip(-2)
    if transpose:
        frames = frames.transpose(-3, -2)
    expected = tracker_velocities(frames, (10, 10))
    assert torch.allclose(flip_aligned(batch, flip_x, flip_y, transpose).velocity[:1], expected, atol=1e-6)


@pytest.mark.parametrize("flips", ALL_FLIPS)
def test_invalid_boxes_stay_zero(flips):
    batch = _batch()
    assert (batch.boxes[~batch.box_valid] == 0).all()
    out = flip_aligned(batch, *flips)
    assert (out.boxes[~out.box_valid] == 0).all()  # a mirrored yaw of 0 would be pi
    assert torch.equal(out.box_valid, batch.box_valid)
    garbage = AlignedBatch(batch.planes, batch.boxes.masked_fill(~batch.box_valid[..., None], 3.0),
                           batch.box_valid, batch.past_actions, batch.future_actions, batch.velocity)
    assert (flip_aligned(garbage, *flips).boxes[~batch.box_valid] == 0).all()


@pytest.mark.parametrize("flips", ALL_FLIPS)
def test_a_flip_and_its_route_command_need_no_host_read_or_host_data(flips):
    """As in a training step on a GPU: nothing waits for the device, nothing is copied to it."""
    batch = _batch()
    flip_aligned(batch, *flips)  # the device constants made once
    with sync_free(), SyncCounter() as counter:
        route_command(flip_aligned(batch, *flips).future_actions)
    assert counter.total == 0 and not counter.host_data, (counter.by_caller, counter.host_data)


def test_only_a_square_plane_can_be_transposed():
    batch = _batch(h=6, w=5)
    with pytest.raises(ValueError, match="square"):
        flip_aligned(batch, False, False, True)
    out = flip_aligned(batch, True, True, False)  # mirroring works on any plane
    assert torch.equal(out.planes.xy, batch.planes.xy.flip(-2, -1))


def test_a_bev_latent_flips_without_height_profiles():
    batch = _batch(bev=True)
    out = flip_aligned(batch, True, True, True)
    assert out.planes.xz is None and out.planes.yz is None
    assert torch.equal(out.planes.xy, batch.planes.xy.flip(-2, -1).transpose(-2, -1))


def test_flips_need_a_grid_centred_on_the_ego(monkeypatch):
    monkeypatch.setattr(latent_flips, "GRID_LOWER", (-30.0, -40.0, -1.0))
    with pytest.raises(ValueError, match="centred on the ego"):
        flip_aligned(_batch(), True, False, False)


def test_random_flips_are_deterministic_with_a_seeded_generator_and_draw_all_eight():
    batch = _batch()
    first, second = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    candidates = {flips: flip_aligned(batch, *flips).planes.xy for flips in ALL_FLIPS}
    drawn = set()
    for _ in range(48):
        a, b = random_flips(batch, first), random_flips(batch, second)
        _assert_same_batch(a, b)
        assert torch.equal(a.boxes, b.boxes)
        which = [flips for flips, xy in candidates.items() if torch.equal(a.planes.xy, xy)]
        assert len(which) == 1
        drawn.add(which[0])
    assert drawn == set(ALL_FLIPS)
