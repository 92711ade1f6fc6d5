"""The flow forecaster: warping, splatting, matching costs, moving a plane, its start as the
present frame, its interface."""

from __future__ import annotations

import math

import pytest
import torch

from t3fast.forecast.records import Agents, Past, Scene
from t3fast.forecast.render import DecodeFrames, KeepObservedStatic, observed_static, present_in_frames
from t3fast.models.flow_forecaster import MOVING_CELLS, FlowTriplaneForecaster, move_plane
from t3fast.models.plane_warp import splat_plane, warp_plane
from t3fast.models.triplane import Triplane


def test_integer_flow_moves_the_plane_by_whole_cells():
    plane = torch.randn(2, 3, 12, 9, dtype=torch.float64)
    flow = torch.zeros(2, 2, 12, 9, dtype=torch.float64)
    flow[:, 0] = -2.0  # content comes from two cells back along dim -2: it moves +2 cells
    flow[:, 1] = 1.0  # and one cell back along dim -1
    out = warp_plane(plane, flow)
    assert torch.allclose(out[:, :, 2:, :-1], plane[:, :, :-2, 1:])
    assert torch.allclose(out[:, :, :2, :-1], plane[:, :, :1, 1:].expand(-1, -1, 2, -1))  # the edge continues


def test_fractional_flow_interpolates_and_is_differentiable():
    plane = torch.randn(1, 2, 6, 7, dtype=torch.float64)
    flow = torch.full((1, 2, 6, 7), 0.25, dtype=torch.float64, requires_grad=True)
    out = warp_plane(plane, flow)
    expected = 0.75 * 0.75 * plane[:, :, 2, 3] + 0.25 * 0.75 * (plane[:, :, 3, 3] + plane[:, :, 2, 4]) \
        + 0.0625 * plane[:, :, 3, 4]
    assert torch.allclose(out[:, :, 2, 3], expected)
    torch.autograd.gradcheck(lambda f: warp_plane(plane, f), (flow,))


def test_warp_refuses_a_flow_of_the_wrong_shape():
    with pytest.raises(ValueError, match=r"flow must have shape \[1, 2, 6, 7\]"):
        warp_plane(torch.zeros(1, 2, 6, 7), torch.zeros(1, 2, 7, 6))


def test_integer_displacement_splats_values_by_whole_cells():
    values = torch.randn(2, 3, 8, 7, dtype=torch.float64)
    disp = torch.zeros(2, 2, 8, 7, dtype=torch.float64)
    disp[:, 0] = 2.0  # each cell's content goes two cells on along dim -2
    disp[:, 1] = -1.0  # and one cell back along dim -1
    out = splat_plane(values, disp)
    assert out.shape == values.shape
    assert torch.allclose(out[:, :, 2:, :-1], values[:, :, :-2, 1:], atol=1e-12)
    assert (out[:, :, :2] == 0).all() and (out[:, :, :, -1] == 0).all()  # nothing lands there


def test_fractional_displacement_splits_with_bilinear_weights():
    values = torch.zeros(1, 2, 6, 7, dtype=torch.float64)
    values[0, :, 2, 3] = torch.tensor([1.0, -2.0])
    disp = torch.zeros(1, 2, 6, 7, dtype=torch.float64)
    disp[0, :, 2, 3] = torch.tensor([0.25, -0.5])  # lands at (2.25, 2.5)
    out = splat_plane(values, disp)
    expected = torch.zeros(6, 7, dtype=torch.float64)
    expected[2, 2], expected[2, 3], expected[3, 2], expected[3, 3] = 0.375, 0.375, 0.125, 0.125
    assert torch.allclose(out[0, 0], expected) and torch.allclose(out[0, 1], -2.0 * expected)
    # what several cells send to the same cell is summed
    values = torch.ones(1, 1, 4, 4, dtype=torch.float64)
    disp = torch.zeros(1, 2, 4, 4, dtype=torch.float64)
    disp[0, 0, 1, 1] = 1.0  # (1, 1) lands on (2, 1), which stays
    assert splat_plane(values, disp)[0, 0, 2, 1] == 2.0 and splat_plane(values, disp)[0, 0, 1, 1] == 0.0


def test_splatting_conserves_what_stays_inside():
    torch.manual_seed(0)
    values = torch.randn(2, 3, 10, 9, dtype=torch.float64)
    values[..., :2, :] = values[..., -2:, :] = 0  # nothing near the edge: nothing can leave
    values[..., :, :2] = values[..., :, -2:] = 0
    disp = torch.rand(2, 2, 10, 9, dtype=torch.float64) * 3.6 - 1.8
    out = splat_plane(values, disp)
    assert torch.allclose(out.sum((-2, -1)), values.sum((-2, -1)))
    assert not torch.allclose(out, values)  # it did move


def test_content_pushed_past_the_edge_is_dropped():
    values = torch.ones(1, 1, 5, 4, dtype=torch.float64)
    disp = torch.zeros(1, 2, 5, 4, dtype=torch.float64)
    disp[:, 0] = 1.5  # row r lands at r + 1.5: half on r + 1, half on r + 2
    out = splat_plane(values, disp)
    assert torch.allclose(out[0, 0, :, 0], torch.tensor([0.0, 0.5, 1.0, 1.0, 1.0], dtype=torch.float64))
    assert torch.allclose(out.sum(), torch.tensor(20.0 - 1.5 * 4, dtype=torch.float64))  # rows 3, 4 partly left
    disp = torch.zeros(1, 2, 5, 4, dtype=torch.float64)
    disp[:, 1] = -10.0  # everything leaves the plane on the left
    assert (splat_plane(values, disp) == 0).all()


def test_splat_is_differentiable_in_values_and_displacement():
    torch.manual_seed(0)
    values = torch.randn(1, 2, 5, 6, dtype=torch.float64, requires_grad=True)
    # fractional parts in [0.3, 0.5]: no cell sits at an integer, where the weights have a kink
    whole = torch.randint(-2, 3, (1, 2, 5, 6)).double()
    disp = (whole + 0.3 + 0.2 * torch.rand(1, 2, 5, 6, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(splat_plane, (values, disp))


def test_splat_refuses_a_displacement_of_the_wrong_shape():
    message = r"splat_plane: displacement must have shape \[1, 2, 6, 7\], got \[1, 2, 7, 6\]"
    with pytest.raises(ValueError, match=message):
        splat_plane(torch.zeros(1, 3, 6, 7), torch.zeros(1, 2, 7, 6))


def test_moving_nothing_leaves_the_plane_as_it_is():
    torch.manual_seed(0)
    present = torch.randn(2, 3, 9, 8)
    out = move_plane(present, torch.zeros(2, 2, 9, 8), torch.full((3,), 5.0))
    assert torch.equal(out, present)  # exactly: a decoder may skip the cells that did not change


def test_cells_nothing_leaves_or_lands_on_keep_their_content_exactly():
    torch.manual_seed(0)
    present = torch.randn(1, 3, 12, 12)
    disp = torch.zeros(1, 2, 12, 12)
    disp[0, 0, 3:5, 4:6] = 1.7
    out = move_plane(present, disp, torch.zeros(3))
    touched = torch.zeros(12, 12, dtype=torch.bool)
    touched[3:7, 4:7] = True  # the block, and the cells its content lands on (bilinear: one more row and column)
    assert torch.equal(out[0][:, ~touched], present[0][:, ~touched])
    assert not torch.allclose(out[0][:, 3:7, 4:6], present[0][:, 3:7, 4:6])


def test_a_moved_block_appears_at_its_new_place_and_leaves_the_fill():
    torch.manual_seed(0)
    present = torch.randn(1, 3, 12, 12)
    fill = torch.tensor([7.0, -7.0, 3.0])
    block = torch.zeros(12, 12, dtype=torch.bool)
    block[3:6, 4:7] = True  # a 3 x 3 agent moving (+2, +1) cells
    disp = torch.zeros(1, 2, 12, 12)
    disp[0, 0][block], disp[0, 1][block] = 2.0, 1.0
    assert 2.0 >= MOVING_CELLS
    out = move_plane(present, disp, fill)
    landed = torch.zeros_like(block)
    landed[5:8, 5:8] = True
    assert torch.allclose(out[:, :, 5:8, 5:8], present[:, :, 3:6, 4:7], atol=1e-4)  # the block, whole
    vacated = block & ~landed  # rows 3, 4 of the block and cell (5, 4)
    assert vacated.sum() == 7
    assert torch.allclose(out[0][:, vacated], fill.view(3, 1).expand(-1, 7), atol=1e-4)
    rest = ~block & ~landed
    assert torch.allclose(out[0][:, rest], present[0][:, rest], atol=1e-4)



def test_a_slow_uniform_motion_keeps_a_constant_plane():
    present = torch.ones(1, 2, 10, 10)
    disp = torch.zeros(1, 2, 10, 10)
    disp[:, 0] = 0.25  # everything moves a quarter cell: the inside of a constant plane stays 1
    out = move_plane(present, disp, torch.zeros(2))
    assert torch.allclose(out[..., 2:8, 2:8], torch.ones(1, 2, 6, 6), atol=1e-3)


def _past(b: int = 2, t: int = 5, c: int = 4, h: int = 20, w: int = 16, z: int = 4) -> Triplane:
    return Triplane(torch.randn(b, t, c, h, w), torch.randn(b, t, c, h, z), torch.randn(b, t, c, w, z))


def test_untrained_forecaster_without_tracked_agents_is_the_present_frame():
    torch.manual_seed(0)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8, 16), steps=3)
    past = _past()
    futures, displacements, deltas = f.predict(past, torch.zeros(2, 4, 20, 16))
    assert len(futures) == 3 and displacements.shape == (2, 3, 2, 20, 16) and deltas.shape == (2, 3, 4, 20, 16)
    assert displacements.abs().max() == 0 and deltas.abs().max() == 0
    for fut in futures:  # nothing moves, Delta 0, the fusion the identity
        assert torch.allclose(fut.xy, past.xy[:, -1], atol=1e-6)
        assert torch.equal(fut.xz, past.xz[:, -1]) and torch.equal(fut.yz, past.yz[:, -1])  # carried
    sum(fut.xy.square().sum() for fut in futures).backward()
    assert f.unet.head.weight.grad.abs().max() > 0  # the zero Delta head learns from the first step


def test_forecaster_reads_matching_costs_of_its_radius_on_any_plane_size():
    torch.manual_seed(0)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(5, 3, 4), widths=(8, 8), steps=2, match_radius=6)
    assert f.match_stem[0].in_channels == 2 * 13 ** 2  # two pairs of frames, 13 x 13 shifts
    futures, displacements, deltas = f.predict(_past(b=1, h=5, w=3), torch.ones(1, 4, 5, 3))  # smaller than the radius
    assert len(futures) == 2 and displacements.shape == (1, 2, 2, 5, 3) and deltas.shape == (1, 2, 4, 5, 3)
    assert torch.isfinite(displacements).all() and all(torch.isfinite(fut.xy).all() for fut in futures)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(6, 6, 4), widths=(8,), history=3, match_radius=0)
    assert f.match_stem[0].in_channels == 2  # two pairs, one shift
    assert f.predict(_past(b=1, t=3, h=6, w=6), torch.zeros(1, 4, 6, 6))[1].shape == (1, 6, 2, 6, 6)


def test_forecaster_interface_and_its_limits():
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8), steps=3)
    past, velocity = _past(b=1), torch.zeros(1, 4, 20, 16)
    futures, changes, displacements = f(past, velocity, 2)
    assert len(futures) == 2 and torch.allclose(changes[0].xy, futures[0].xy - past.xy[:, -1])
    assert displacements.shape == (1, 2, 2, 20, 16)
    with pytest.raises(ValueError, match="from the observed history at once; asked for 4 steps"):
        f(past, velocity, 4)
    with pytest.raises(ValueError, match="5 history frames needed, got 3"):
        f.predict(past.map(lambda p: p[:, -3:]), velocity)
    with pytest.raises(ValueError, match="reads the 3 history frames the tracker's velocities come from, got 2"):
        FlowTriplaneForecaster(history=2)


@pytest.mark.parametrize("bad, message", [
    (dict(forecaster="lstm"), "'forecaster' must be 'delta' or 'flow'"),
    (dict(flow_widths=[12]), r"'flow_widths\[0\]' must be a multiple of 8"),
    (dict(flow_widths=[]), "'flow_widths' must be a list of 1 to"),
    (dict(flow_scale=0), "'flow_scale' must be a number in"),
    (dict(match_radius=-1), r"'match_radius' must be an integer in \[0, 16\], got -1"),
    (dict(match_radius=2.5), r"'match_radius' must be an integer in \[0, 16\], got 2.5"),
    (dict(match_radius=17), r"'match_radius' must be an integer in \[0, 16\], got 17"),
])
def test_flow_config_refuses_bad_values(bad, message):
    from t3fast.errors import ConfigError
    from t3fast.models.config import WorldModelConfig

    with pytest.raises(ConfigError, match=message):
        WorldModelConfig(**bad)


def test_world_model_builds_the_forecaster_its_config_names():
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig

    ae = AutoencoderConfig(embed_dim=4, full_res_channels=4, full_res_blocks=0, half_res_channels=8,
                           half_res_blocks=0, channels=4, decoder_channels=8, decoder_hidden=[16])
    world = WorldModelConfig(forecaster="flow", flow_widths=[8, 8], planner_widths=[8, 8, 8, 8], d_act=10,
                             planner_heads=2, ego_aligned=True)
    from t3fast.training.world_model.forwards import FlowMotionModel

    model = FlowMotionModel.from_config(ae, world)
    assert isinstance(model.forecaster, FlowTriplaneForecaster)
    past = Triplane(torch.randn(1, 5, 4, 100, 100), torch.randn(1, 5, 4, 100, 16), torch.randn(1, 5, 4, 100, 16))
    assert model.forecaster.match_radius == world.match_radius == 6
    futures, displacements, deltas, actions = model(past, torch.zeros(1, 4, 100, 100))
    assert actions is None  # no route planner inputs
    assert len(futures) == 6 and displacements.shape == (1, 6, 2, 100, 100) and deltas.shape == (1, 6, 4, 100, 100)
    pipeline = model.pipeline
    past_record = Past(torch.zeros(1, 5, 1, 1, 1), torch.zeros(1, 5, 3), torch.zeros(1, 4, 2), past)
    scene = pipeline.scene(past_record, Agents(velocity=torch.zeros(1, 4, 100, 100)), 6)
    assert len(scene.futures) == 6 and pipeline.plan(past_record, scene, None).actions.shape == (1, 6, 2)


def test_untrained_forecaster_moves_agents_along_their_velocities():
    torch.manual_seed(0)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8, 16), steps=3)
    assert f.unet.down[0][0].in_channels == 9 * 4 + 32 + 4  # both velocity fields are inputs too
    past = _past()
    velocity = torch.zeros(2, 4, 20, 16)
    velocity[0, :, 5:8, 4:7] = torch.tensor([1.5, -1.0, 1.0, -1.0]).view(4, 1, 1)  # accelerating
    _, displacements, _ = f.predict(past, velocity)
    blend = torch.zeros(2, 2, 20, 16)
    blend[0, :, 5:8, 4:7] = torch.tensor([1.25, -1.0]).view(2, 1, 1)  # last step and two-step mean averaged
    for k in range(3):  # step k: k + 1 blended velocities; the motion head's correction starts at zero
        assert torch.equal(displacements[:, k], (k + 1) * blend)
    assert f.unet.head.out_channels == 3 * 4  # the UNet predicts Delta only
    futures, _, _ = f(past, velocity, 2)
    assert len(futures) == 2
    with pytest.raises(ValueError, match=r"needs the agents' velocities \[2, 4, 20, 16\].*got None"):
        f.predict(past, None)
    with pytest.raises(ValueError, match=r"needs the agents' velocities \[2, 4, 20, 16\].*got \[2, 2, 20, 16\]"):
        f.predict(past, velocity[:, :2])


def test_motion_head_corrects_the_tracked_agents_only():
    torch.manual_seed(0)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8, 16), steps=3)
    torch.nn.init.normal_(f.motion_head.head[-1].bias)  # a trained head: a correction wherever it is asked
    velocity = torch.zeros(2, 4, 20, 16)
    velocity[0, :, 5:8, 4:7] = torch.tensor([1.5, -1.0, 1.0, -1.0]).view(4, 1, 1)
    velocity[1, 2:, 10, 10] = 0.5  # matched two steps back only: still a tracked agent
    _, displacements, _ = f.predict(_past(), velocity)
    tracked = (velocity != 0).any(1)
    assert (displacements.abs().sum(2)[:, :, ~tracked[0] & ~tracked[1]] == 0).all()  # the static world stays
    prior = torch.stack([(k + 1) * velocity[:, :2] for k in range(3)], 1)
    assert (displacements - prior).abs().sum(2)[0, :, 6, 5].min() > 0
    assert (displacements - prior).abs().sum(2)[1, :, 10, 10].min() > 0
    loss = displacements.square().sum()
    loss.backward()
    assert f.motion_head.head[-1].weight.grad.abs().sum() > 0  # the zero-initialised head learns from step 1


def test_world_model_with_a_flow_forecaster_measures_velocities_from_the_past_frames():
    from t3fast.data.classes import CAR, FREE
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig
    from t3fast.models.world_model import T3Former

    ae = AutoencoderConfig(embed_dim=4, full_res_channels=4, full_res_blocks=0, half_res_channels=8,
                           half_res_blocks=0, channels=4, decoder_channels=8, decoder_hidden=[16])
    world = WorldModelConfig(forecaster="flow", flow_widths=[8, 8], planner_widths=[8, 8, 8, 8], d_act=10,
                             planner_heads=2, ego_aligned=True)
    model = T3Former.from_config(ae, world).eval()
    occ = torch.full((1, 5, 200, 200, 16), FREE, dtype=torch.uint8)
    for t in range(5):  # a car speeding up along x by 2 grid cells a frame each frame; the ego stands still
        occ[0, t, 60 + t * (t + 1) : 70 + t * (t + 1), 100:104, 0:3] = CAR
    still = torch.zeros(1, 4, 2)
    past = model.pipeline.encode(occ, still)
    velocity = model.pipeline.agents(past).velocity
    assert velocity.shape == (1, 4, 100, 100)
    # last step 8 grid cells = 4 plane cells; the mean of the last two steps 7 grid cells
    assert torch.allclose(velocity[0, :, 42, 51], torch.tensor([4.0, 0.0, 3.5, 0.0]))
    assert model.forecast(occ, still).labels.shape == (1, 6, 200, 200, 16)
    with pytest.raises(ValueError, match="needs the agents' velocities"):
        model.pipeline.scene(past, Agents(), 6)
    world.forecaster = "delta"
    untracked = T3Former.from_config(ae, world).pipeline
    assert untracked.agents(untracked.encode(occ, still)).velocity is None  # the Delta forecaster reads none


def test_rendering_only_the_changed_voxels_gives_the_labels_of_decoding_all():
    """The world model's render decodes only the voxels near cells the forecast changed (and
    those beyond the present grid); the labels equal decoding every voxel, for a flow forecast
    that moves a few agents, and for one that changes every plane."""
    from t3fast.data.classes import AGENT_CLASSES, CAR, FREE, MANMADE
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig
    from t3fast.models.world_model import T3Former

    torch.manual_seed(0)
    ae = AutoencoderConfig(embed_dim=4, full_res_channels=4, full_res_blocks=0, half_res_channels=8,
                           half_res_blocks=0, channels=4, decoder_channels=8, decoder_hidden=[16])
    world = WorldModelConfig(forecaster="flow", flow_widths=[8, 8], planner_widths=[8, 8, 8, 8], d_act=10,
                             planner_heads=2, ego_aligned=True)
    model = T3Former.from_config(ae, world).eval()
    occ = torch.randint(0, 17, (1, 5, 200, 200, 16), dtype=torch.uint8)
    occ[torch.isin(occ, torch.tensor(AGENT_CLASSES, dtype=torch.uint8))] = MANMADE  # a static world
    occ[:, :, 50:150, 50:150] = FREE
    for t in range(5):  # two cars driving, the ego moving forward 2 m a frame
        occ[0, t, 60 + 3 * t : 70 + 3 * t, 100:104, 0:3] = CAR
        occ[0, t, 120:124, 70 + 2 * t : 80 + 2 * t, 0:3] = CAR
    poses = torch.stack([torch.tensor([2.0 * (t - 4), 0.0, 0.0]) for t in range(5)])[None]
    pipeline = model.pipeline
    past = Past(occ, poses, poses[:, 1:, :2] - poses[:, :-1, :2], pipeline.encode.planes(occ, poses))
    scene = pipeline.scene(past, pipeline.agents(past), 6)
    frames = torch.stack([torch.tensor([2.0 * (k + 1), 0.3 * k, 0.02 * k]) for k in range(6)])[None]
    moved_cells = (scene.futures[5].xy != past.present_planes.xy).any(1).float().mean()
    assert 0 < moved_cells < 0.2
    changed = Scene([f.map(lambda p: p + 0.1) for f in scene.futures], scene.changes, None)  # every voxel decoded
    for forecast in (scene, changed):
        decoded = DecodeFrames(model.decoder, True)(past, forecast, None, frames)
        moved = present_in_frames(occ[:, -1], frames)
        present = DecodeFrames(model.decoder, True)(past, Scene([past.present_planes] * 6, [], None), None, frames)
        agents = torch.tensor(AGENT_CLASSES)
        reference = torch.where(torch.isin(decoded, agents) | torch.isin(moved, agents), present, decoded)
        full = observed_static(decoded, reference, moved)  # every voxel decoded
        assert torch.equal(KeepObservedStatic(model.decoder)(past, forecast, None, frames), full)


def _render_agents_model(render_agents: bool = True, agent_boxes: bool = False):
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig
    from t3fast.models.world_model import T3Former

    ae = AutoencoderConfig(embed_dim=4, full_res_channels=4, full_res_blocks=0, half_res_channels=8,
                           half_res_blocks=0, channels=4, decoder_channels=8, decoder_hidden=[16])
    world = WorldModelConfig(forecaster="flow", flow_widths=[8, 8], planner_widths=[8, 8, 8, 8], d_act=10,
                             planner_heads=2, ego_aligned=True, render_agents=render_agents,
                             agent_boxes=agent_boxes)
    return T3Former.from_config(ae, world).eval()


def test_untrained_agent_render_moves_the_agents_as_the_tracker_does():
    """With an untrained motion head the forecaster's displacements are the tracker's velocities
    (here at constant speed, so the chain blend is the last step's velocity), and the label-space
    render draws the present agents exactly where the tracker baseline puts them; a trained
    head's correction moves them elsewhere."""
    from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, PEDESTRIAN
    from t3fast.evaluation.baselines import track_agents

    torch.manual_seed(0)
    model = _render_agents_model()
    occ = torch.full((1, 5, 200, 200, 16), FREE, dtype=torch.uint8)
    occ[..., 0] = DRIVEABLE_SURFACE
    for t in range(5):  # a car at 6 grid cells a frame, a pedestrian at 1, a parked car
        occ[0, t, 40 + 6 * t : 50 + 6 * t, 100:104, 1:3] = CAR
        occ[0, t, 150, 60 + t : 62 + t, 1:4] = PEDESTRIAN
        occ[0, t, 150:160, 150:154, 1:3] = CAR
    poses = torch.zeros(1, 5, 3)  # the ego stands still: every future voxel was seen
    still = torch.zeros(1, 6, 3)
    labels = model.forecast(occ, torch.zeros(1, 4, 2), future_actions=still).labels
    expected = track_agents(occ, poses, still)
    assert torch.equal(labels, expected)
    assert (labels[0, 5, 100:110, 100:104, 1] == CAR).all()  # 6 steps of 6 cells on from 64
    with torch.no_grad():
        model.forecaster.motion_head.head[-1].bias.fill_(0.5)  # a trained head's correction
    moved = model.forecast(occ, torch.zeros(1, 4, 2), future_actions=still).labels
    assert not torch.equal(moved, expected)


def test_agent_render_fills_what_the_present_never_saw_from_the_forecast():
    from t3fast.data.classes import FLAT_GROUND_CLASSES, FREE, IGNORE

    torch.manual_seed(0)
    model = _render_agents_model()
    occ = torch.randint(0, 17, (1, 5, 200, 200, 16), dtype=torch.uint8)
    poses = torch.stack([torch.tensor([4.0 * (t - 4), 0.0, 0.0]) for t in range(5)])[None]
    ahead = torch.stack([torch.tensor([4.0 * (k + 1), 0.0, 0.0]) for k in range(6)])[None]  # 24 m on
    out = model.forecast(occ, poses[:, 1:, :2] - poses[:, :-1, :2], future_actions=ahead)
    labels = out.labels
    assert not (labels == IGNORE).any()
    beyond = labels[0, 5, -30:]  # the last 12 m of the last frame lie beyond the present grid
    allowed = torch.tensor(list(FLAT_GROUND_CLASSES) + [FREE], dtype=labels.dtype)
    assert torch.isin(beyond, allowed).all()


def test_agents_drawn_as_fitted_boxes_land_where_the_data_draws_them():
    """A car at 1.1 m and a pedestrian at 0.5 m a step, drawn by the synthetic data's renderer in
    11 frames while the ego drives: moved as their fitted boxes (the untrained forecaster's
    tracker displacement, not rounded to cells), the forecast overlaps the true future agents
    more than the same agents' voxels moved by whole cells."""
    import numpy as np

    from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, PEDESTRIAN
    from t3fast.data.synthetic.render import draw_boxes
    from t3fast.models.ego_motion import relative

    torch.manual_seed(0)
    frames = []
    poses = torch.stack([torch.tensor([1.3 * (t - 4), 0.0, 0.0], dtype=torch.float64) for t in range(11)])
    for t in range(11):
        boxes = torch.tensor([[-6.07 + 1.1 * (t - 4), 3.33, 0.3, 4.5, 1.9, 1.6, 0.0],
                              [5.11, -8.29 + 0.5 * (t - 4), 0.3, 0.6, 0.6, 1.8, math.pi / 2]], dtype=torch.float64)
        local = relative(poses[t].expand(2, 3), boxes[:, [0, 1, 6]])
        boxes[:, 0], boxes[:, 1], boxes[:, 6] = local[:, 0], local[:, 1], local[:, 2]
        frame = np.full((200, 200, 16), FREE, dtype=np.uint8)
        frame[..., 0] = DRIVEABLE_SURFACE
        draw_boxes(frame, boxes.numpy(), np.array([CAR, PEDESTRIAN]))
        frames.append(torch.from_numpy(frame))
    occ = torch.stack(frames)[None]
    past_actions = (poses[1:5, :2] - poses[:4, :2]).float()[None]
    future = poses[5:].float()[None]
    truth = occ[0, 5:]
    scores = []
    for boxes in (False, True):
        model = _render_agents_model(agent_boxes=boxes)
        labels = model.forecast(occ[:, :5], past_actions, future_actions=future).labels[0]
        agents = torch.isin(truth, torch.tensor([CAR, PEDESTRIAN], dtype=truth.dtype))
        drawn = torch.isin(labels, torch.tensor([CAR, PEDESTRIAN], dtype=labels.dtype))
        scores.append(float((agents & drawn & (labels == truth)).sum() / (agents | drawn).sum()))
    assert scores[1] > scores[0] + 0.03, scores  # 0.81 against 0.76


def test_agent_render_needs_the_flow_forecaster():
    from t3fast.errors import ConfigError
    from t3fast.models.config import WorldModelConfig

    with pytest.raises(ConfigError, match="'render_agents' .* needs forecaster='flow', got 'delta'"):
        WorldModelConfig(forecaster="delta", render_agents=True)
    with pytest.raises(ConfigError, match="'render_agents' must be true or false, got 1"):
        WorldModelConfig(forecaster="flow", render_agents=1)
    with pytest.raises(ConfigError, match="'agent_boxes' draws the agents 'render_agents' moves .* render_agents"):
        WorldModelConfig(forecaster="flow", agent_boxes=True)
    from t3fast.models.world_model import T3Former

    parts = _render_agents_model(render_agents=False)
    with pytest.raises(ValueError, match="agent_boxes draws the agents render_agents moves .* needs render_agents"):
        T3Former(parts.encoder, parts.forecaster, parts.planner, parts.decoder, ego_aligned=True, agent_boxes=True)


def test_context_motion_head_starts_as_the_tracker_and_reads_the_scene():
    torch.manual_seed(0)
    f = FlowTriplaneForecaster(channels=4, plane_shape=(20, 16, 4), widths=(8, 8, 16), steps=3)
    past = _past()
    velocity = torch.zeros(2, 4, 20, 16)
    velocity[0, :, 5:8, 4:7] = torch.tensor([1.5, -1.0, 1.0, -1.0]).view(4, 1, 1)
    _, displacements, _ = f.predict(past, velocity)
    for k in range(3):  # untrained: the tracker's blended motion exactly
        assert torch.equal(displacements[:, k], (k + 1) * (velocity[:, :2] + velocity[:, 2:]) / 2)
    displacements.square().sum().backward()
    assert f.motion_head.head[-1].weight.grad.abs().sum() > 0  # learns from step 1
    torch.nn.init.normal_(f.motion_head.head[-1].weight, std=0.1)
    with torch.no_grad():
        _, before, _ = f.predict(past, velocity)
        far = past.map(lambda p: p.clone())
        far.xy[:, -1, :, 15:, 10:] += 1.0  # the scene changes 8 cells away from the agent
        _, after, _ = f.predict(far, velocity)
    assert (before[0, :, :, 6, 5] - after[0, :, :, 6, 5]).abs().max() > 0  # the agent's motion reads it
    assert (after[:, :, :, (velocity == 0).all(1)[0]] == 0).all()  # the untracked world stays still


def test_configs_of_earlier_versions_load_without_their_removed_flow_switches():
    """Checkpoints name tracker_prior / motion_context, which the flow forecaster now always has."""
    from t3fast.errors import ConfigError
    from t3fast.io.config import load_config
    from t3fast.models.config import WorldModelConfig

    flow = load_config(WorldModelConfig, {"forecaster": "flow", "tracker_prior": True, "motion_context": True})
    assert flow.forecaster == "flow" and not hasattr(flow, "tracker_prior")
    delta = load_config(WorldModelConfig, {"forecaster": "delta", "tracker_prior": False, "motion_context": False})
    assert delta.forecaster == "delta"
    for key in ("tracker_prior", "motion_context"):
        with pytest.raises(ConfigError, match=f"'{key}=false' is no longer supported"):
            load_config(WorldModelConfig, {"forecaster": "flow", key: False})
        with pytest.raises(ConfigError, match=f"'{key}=false' is no longer supported"):
            load_config(WorldModelConfig, {"forecaster": "flow"}, overrides=[f"{key}=false"])
