"""The tracker's agent velocities as a field on the xy plane (the flow forecaster's prior)."""

from __future__ import annotations

import pytest
import torch

from t3fast import ops
from t3fast.agents.tracker import agent_velocity_field, tracker_velocities
from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, PEDESTRIAN


def _frames(x: int = 20, y: int = 20, z: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    present = torch.full((1, x, y, z), FREE, dtype=torch.uint8)
    present[..., 0] = DRIVEABLE_SURFACE
    return present, present.clone()


def test_a_moving_car_carries_its_velocity_in_plane_cells_and_the_rest_stands_still():
    present, previous = _frames()
    previous[0, 2:6, 8:10, 1:3] = CAR  # 4 grid cells forward and 2 to the right per step
    present[0, 6:10, 10:12, 1:3] = CAR
    field = agent_velocity_field(present, previous, (10, 10))
    assert field.shape == (1, 2, 10, 10) and field.dtype == torch.float32
    car = torch.zeros(10, 10, dtype=torch.bool)
    car[3:5, 5:6] = True  # the plane cells of the car's columns (2 grid cells each)
    assert torch.allclose(field[0, :, car], torch.tensor([[2.0], [1.0]]))
    ring = torch.nn.functional.max_pool2d(car[None].float(), 3, 1, 1)[0].bool() & ~car
    assert torch.allclose(field[0, :, ring], torch.tensor([[2.0], [1.0]]))  # its latent spreads a cell
    assert (field[0, :, ~(car | ring)] == 0).all()


def test_an_unmatched_or_standing_agent_has_no_velocity():
    present, previous = _frames()
    present[0, 2:4, 2:4, 1] = PEDESTRIAN  # standing
    previous[0, 2:4, 2:4, 1] = PEDESTRIAN
    present[0, 14:18, 14:16, 1] = CAR  # no car in the previous frame: nothing to match
    previous[0, 14:18, 4:6, 1] = PEDESTRIAN  # another class does not match
    assert (agent_velocity_field(present, previous, (10, 10)) == 0).all()
    far = previous.clone()
    far[0, 2:6, 14:16, 1] = CAR  # 12 grid cells = 4.8 m away: within the default 8 m gate, beyond 4 m
    assert (agent_velocity_field(present, far, (10, 10), gate=4.0)[0, :, 7:9, 7] == 0).all()
    assert torch.allclose(agent_velocity_field(present, far, (10, 10))[0, :, 7:9, 7], torch.tensor([[6.0], [0.0]]))


def test_an_odd_grid_maps_onto_its_rounded_up_plane():
    present, previous = _frames(x=9, y=7)
    previous[0, 0:2, 0:2, 1] = CAR
    present[0, 2:4, 0:2, 1] = CAR  # 2 grid cells = 1 plane cell along x
    field = agent_velocity_field(present, previous, (5, 4))
    assert field.shape == (1, 2, 5, 4)
    assert torch.allclose(field[0, :, 1, 0], torch.tensor([1.0, 0.0]))


def test_frames_of_different_shapes_are_refused():
    present, previous = _frames()
    with pytest.raises(ValueError, match="previous .* and present .* differ"):
        agent_velocity_field(present, previous[..., :3], (10, 10))


def test_tracker_velocities_are_the_last_step_and_the_mean_of_the_last_two():
    frames = torch.full((1, 3, 20, 20, 4), FREE, dtype=torch.uint8)
    for t, x in enumerate([0, 2, 8]):  # 2 then 6 grid cells a step: braking would read the other way round
        frames[0, t, x : x + 4, 8:10, 1] = CAR
    v = tracker_velocities(frames, (10, 10))
    assert v.shape == (1, 4, 10, 10)
    assert torch.allclose(v[0, :, 4, 4], torch.tensor([3.0, 0.0, 2.0, 0.0]))  # plane cells per step
    with pytest.raises(ValueError, match=r"frames must be \[B, 3, X, Y, Z\], got \[1, 2, 20, 20, 4\]"):
        tracker_velocities(frames[:, 1:], (10, 10))


def test_two_step_velocity_follows_the_matched_chain_not_the_nearest_car_two_frames_back():
    frames = torch.full((1, 3, 40, 20, 4), FREE, dtype=torch.uint8)
    for t in range(3):  # a queue of two cars 11 cells apart, each at 5 cells a step
        for start in (0, 11):
            frames[0, t, start + 5 * t : start + 5 * t + 3, 8:10, 1] = CAR
    v = tracker_velocities(frames, (20, 10))
    # the rear car now (x 10..12) sits where the front car was two frames back: matched directly
    # it would not have moved; along the chain it moved 10 cells in two steps
    assert torch.allclose(v[0, :, 5, 4], torch.tensor([2.5, 0.0, 2.5, 0.0]))
    assert torch.allclose(v[0, :, 11, 4], torch.tensor([2.5, 0.0, 2.5, 0.0]))


def test_a_bev_covered_by_agents_everywhere_is_one_component():
    labels, n = ops.bev_components(torch.ones(1, 5, 4, dtype=torch.bool))
    assert n.tolist() == [1] and torch.equal(labels[0], torch.ones(5, 4, dtype=torch.long))
    present = torch.full((1, 6, 6, 2), CAR, dtype=torch.uint8)  # every column holds an agent
    assert (agent_velocity_field(present, present.clone(), (3, 3)) == 0).all()


def test_move_agents_pastes_each_component_at_its_shift_and_frees_where_it_was():
    from t3fast.agents.tracker import frame_agents, move_agents
    from t3fast.data.classes import AGENT_CLASSES

    frame, _ = _frames()
    frame = frame[0]
    frame[2:6, 2:4, 1:3] = CAR
    frame[12:14, 12:14, 1] = PEDESTRIAN
    agents = frame_agents(frame, torch.tensor(AGENT_CLASSES, dtype=torch.uint8))
    order = agents["ids"][3, 3] - 1, agents["ids"][12, 12] - 1  # car, pedestrian components
    shift = torch.zeros(2, 2, 2, dtype=torch.long)
    shift[1, order[0]] = torch.tensor([3, 1])  # step 1: the car moves, the pedestrian stays
    shift[1, order[1]] = torch.tensor([0, 10])  # and the pedestrian leaves the grid
    moved = move_agents(frame, agents, shift, FREE)
    assert moved.shape == (2, 20, 20, 4)
    assert torch.equal(moved[0], frame)  # no shift: the frame as it was
    expected = frame.clone()
    expected[torch.isin(frame, torch.tensor([CAR, PEDESTRIAN], dtype=torch.uint8))] = FREE
    expected[5:9, 3:5, 1:3] = CAR  # heights kept, ground under it untouched
    assert torch.equal(moved[1], expected)


def test_component_shifts_average_the_displacement_over_each_agent_in_grid_cells():
    from t3fast.agents.tracker import component_shifts, frame_agents
    from t3fast.data.classes import AGENT_CLASSES

    frame, _ = _frames()
    frame = frame[0]
    frame[2:6, 2:4, 1] = CAR  # plane cells (1..2, 1) at 2 grid cells per plane cell
    agents = frame_agents(frame, torch.tensor(AGENT_CLASSES, dtype=torch.uint8))
    displacement = torch.zeros(3, 2, 10, 10)
    displacement[1, :, 1, 1] = torch.tensor([1.0, -0.5])
    displacement[1, :, 2, 1] = torch.tensor([2.0, -0.5])  # the car's two plane cells disagree: their mean
    shifts = component_shifts(agents, displacement)
    assert shifts.shape == (3, 1, 2)
    assert torch.allclose(shifts[1, 0], torch.tensor([3.0, -1.0], dtype=torch.float64))
    assert (shifts[[0, 2]] == 0).all()
    empty = frame_agents(frame.masked_fill(frame == CAR, FREE), torch.tensor(AGENT_CLASSES, dtype=torch.uint8))
    assert component_shifts(empty, displacement).shape == (3, 0, 2)


def _busy_frame(seed: int = 0) -> torch.Tensor:
    """A frame of many agents of mixed classes (some components of two), on a ground floor."""
    from t3fast.data.classes import AGENT_CLASSES

    g = torch.Generator().manual_seed(seed)
    frame = torch.full((40, 36, 6), FREE, dtype=torch.uint8)
    frame[..., 0] = DRIVEABLE_SURFACE
    classes = torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    for _ in range(30):
        r, c = torch.randint(0, 37, (1,), generator=g).item(), torch.randint(0, 33, (1,), generator=g).item()
        z = torch.randint(1, 4, (1,), generator=g).item()
        frame[r : r + 3, c : c + 2, z : z + 2] = classes[torch.randint(0, len(classes), (1,), generator=g)]
    return frame


@pytest.mark.parametrize("seed", [0, 1])
def test_agents_in_fixed_slots_are_the_counted_agents_and_empty_slots_after_them(seed):
    from t3fast.agents.tracker import agent_levels, frame_agents
    from t3fast.data.classes import AGENT_CLASSES
    from t3fast.host_syncs import sync_free

    frame, classes = _busy_frame(seed), torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    counted = frame_agents(frame, classes)
    n = counted["cls"].shape[0]
    assert 10 < n < 40 and counted["valid"].all()
    with sync_free():  # the votes from every voxel, as on a GPU
        fixed = frame_agents(frame, classes, slots=48)
    assert torch.equal(fixed["ids"], counted["ids"]) and torch.equal(fixed["mask"], counted["mask"])
    assert fixed["valid"].tolist() == [True] * n + [False] * (48 - n)
    for key in ("cls", "votes", "centroid"):
        assert torch.equal(fixed[key][:n], counted[key]), key
    assert (fixed["cls"][n:] == -1).all() and (fixed["votes"][n:] == 0).all()
    bottom, top = agent_levels(counted)
    assert torch.equal(torch.stack(agent_levels(fixed))[:, :n], torch.stack([bottom, top]))
    ijz = counted["mask"].nonzero()  # the levels of every agent's voxels, one by one
    slot = counted["ids"][ijz[:, 0], ijz[:, 1]] - 1
    assert torch.equal(bottom, torch.full((n,), 6).scatter_reduce(0, slot, ijz[:, 2], "amin"))
    assert torch.equal(top, torch.zeros(n, dtype=torch.long).scatter_reduce(0, slot, ijz[:, 2] + 1, "amax"))


def test_components_beyond_the_slots_are_not_agents():
    from t3fast.agents.tracker import frame_agents
    from t3fast.data.classes import AGENT_CLASSES

    frame, classes = _busy_frame(), torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    counted = frame_agents(frame, classes)
    few = frame_agents(frame, classes, slots=5)
    assert few["valid"].all() and few["ids"].max() == 5
    assert torch.equal(few["ids"], torch.where(counted["ids"] <= 5, counted["ids"], 0))
    assert torch.equal(few["mask"], counted["mask"] & (few["ids"] > 0)[..., None])
    assert torch.equal(few["centroid"], counted["centroid"][:5])


def test_moving_agents_in_slots_without_host_reads_gives_the_compacted_result():
    """Every voxel at once (a GPU run) against the agents' voxels found on the host: the same
    frames, where agents land on one another (the later in row-major order wins) and leave the
    grid, and with some agents kept out (drawn as boxes)."""
    from t3fast.agents.tracker import frame_agents, move_agents
    from t3fast.data.classes import AGENT_CLASSES
    from t3fast.host_syncs import sync_free

    frame, classes = _busy_frame(2), torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    agents = frame_agents(frame, classes)
    n = agents["cls"].shape[0]
    shift = torch.randint(-6, 7, (4, n, 2), generator=torch.Generator().manual_seed(3))
    keep = torch.arange(n) % 3 != 0
    for kept in (None, keep):
        compacted = move_agents(frame, agents, shift, FREE, keep=kept)
        with sync_free():
            assert torch.equal(move_agents(frame, agents, shift, FREE, keep=kept), compacted)
    assert (compacted != frame).any()


def test_the_frames_of_several_windows_at_once_are_each_frame_alone():
    """With fixed slots, frame_agents takes frames ``[..., X, Y, Z]`` (a GPU forecast finds every
    window's agents in one call): each frame's records are those of the frame alone."""
    from t3fast.agents.tracker import frame_agents, frame_of
    from t3fast.data.classes import AGENT_CLASSES

    frames = torch.stack([torch.stack([_busy_frame(3 * b + t) for t in range(3)]) for b in range(2)])
    classes = torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    every = frame_agents(frames, classes, slots=40)
    assert every["ids"].shape == (2, 3, 40, 36) and every["column_slot"].shape == (2, 3, 40 * 36)
    for b in range(2):
        for t in range(3):
            alone, got = frame_agents(frames[b, t], classes, slots=40), frame_of(frame_of(every, b), t)
            for key in ("ids", "mask", "valid", "cls", "votes", "centroid"):
                assert torch.equal(got[key], alone[key]), (b, t, key)
    with pytest.raises(ValueError, match="need fixed slots"):
        frame_agents(frames, classes)


def test_unobserved_voxels_vote_for_no_class_in_fixed_slots():
    """Frames with unobserved voxels (255, also in agents' columns and in the last frame, whose
    rows end the votes): each frame's agents in slots are those of the frame alone."""
    from t3fast.agents.tracker import frame_agents, frame_of
    from t3fast.data.classes import AGENT_CLASSES, IGNORE

    frames = torch.stack([_busy_frame(7), _busy_frame(8)])
    frames[..., -1] = IGNORE
    frames[1, :20, :, 4] = IGNORE
    classes = torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    every = frame_agents(frames, classes, slots=40)
    for b in range(2):
        alone, got = frame_agents(frames[b], classes, slots=40), frame_of(every, b)
        for key in ("ids", "mask", "valid", "cls", "votes"):
            assert torch.equal(got[key], alone[key]), (b, key)
    assert int(every["votes"].sum()) == int(every["mask"].sum()) > 0


def test_moving_several_windows_agents_at_once_is_each_window_alone():
    from t3fast.agents.tracker import frame_agents, frame_of, move_agents
    from t3fast.data.classes import AGENT_CLASSES
    from t3fast.host_syncs import sync_free

    frames, classes = torch.stack([_busy_frame(4), _busy_frame(5)]), torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
    g = torch.Generator().manual_seed(6)
    with sync_free():
        every = frame_agents(frames, classes, slots=40)
        shift = torch.randint(-6, 7, (2, 3, 40, 2), generator=g)
        keep = torch.rand(2, 40, generator=g) > 0.3
        for kept in (None, keep):
            together = move_agents(frames, every, shift, FREE, keep=kept)
            for b in range(2):
                one = None if kept is None else kept[b]
                alone = move_agents(frames[b], frame_of(every, b), shift[b], FREE, keep=one)
                assert torch.equal(together[b], alone), b
