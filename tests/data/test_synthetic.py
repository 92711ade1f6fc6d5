
import numpy as np
import pytest
import torch

from t3fast.data import classes as C
from t3fast.data.sample import PRESENT, WINDOW, actions_from_poses, collate_samples, flip_sample
from t3fast.data.stats import constant_velocity_error
from t3fast.data.synthetic.dataset import SPLIT_SEEDS, SPLIT_SIZE, SyntheticDriving, SyntheticFrames, scene_seed
from t3fast.data.synthetic.render import render_static
from t3fast.data.synthetic.scene import ego_xy_yaw, generate_scene, simulate_scene, world_to_ego
from t3fast.data.synthetic.world import GROUND_CLASSES, GROUND_Z, z_level


def test_generation_is_deterministic_and_seed_dependent():
    a, b, c = generate_scene(7, 12), generate_scene(7, 12), generate_scene(8, 12)
    for field in ("occ", "mask_camera", "ego_poses", "boxes_world", "labels"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert (a.occ != c.occ).mean() > 0.01


def test_dataset_samples_are_deterministic(synthetic):
    fresh = SyntheticDriving(synthetic.scenes.split, synthetic.scenes.num_scenes, synthetic.scenes.frames_per_scene)
    x, y = synthetic[2], fresh[2]
    assert torch.equal(x.occ, y.occ) and torch.equal(x.boxes, y.boxes)
    assert torch.equal(x.future_actions, y.future_actions)


def test_splits_use_disjoint_seeds_and_differ():
    ranges = {s: set(range(SPLIT_SEEDS[s], SPLIT_SEEDS[s] + SPLIT_SIZE, 9973)) for s in SPLIT_SEEDS}
    assert not (ranges["train"] & ranges["val"] or ranges["train"] & ranges["test"] or ranges["val"] & ranges["test"])
    seeds = {s: {scene_seed(s, k) for k in range(50)} for s in SPLIT_SEEDS}
    assert len(seeds["train"] | seeds["val"] | seeds["test"]) == 150
    with pytest.raises(ValueError):
        scene_seed("train", SPLIT_SIZE)
    with pytest.raises(ValueError):
        scene_seed("holdout", 0)
    frames = [SyntheticFrames(s, num_scenes=1, frames_per_scene=11)[0] for s in ("train", "val", "test")]
    assert not torch.equal(frames[0], frames[1]) and not torch.equal(frames[1], frames[2])


def test_sample_shapes_and_dtypes(synthetic):
    s = synthetic[0]
    a = s.box_labels.shape[0]
    assert a > 0
    assert s.occ.shape == (WINDOW, 200, 200, 16) and s.occ.dtype == torch.uint8
    assert s.mask_camera.shape == s.occ.shape and s.mask_camera.dtype == torch.bool
    assert s.past_actions.shape == (4, 2) and s.past_actions.dtype == torch.float32
    assert s.future_actions.shape == (6, 2) and s.future_actions.dtype == torch.float32
    assert s.boxes.shape == (WINDOW, a, 7) and s.boxes.dtype == torch.float32
    assert s.box_valid.shape == (WINDOW, a) and s.box_valid.dtype == torch.bool
    assert s.box_labels.dtype == torch.int64 and set(s.box_labels.tolist()) <= set(C.AGENT_CLASSES)
    assert s.ego_poses.shape == (WINDOW, 4, 4) and s.ego_poses.dtype == torch.float32
    assert s.past_occ.shape[0] == 5 and s.future_occ.shape[0] == 6
    assert torch.equal(s.past_occ[-1], s.occ[PRESENT])
    assert int(s.occ.max()) <= C.FREE
    assert len(synthetic) == 2 * (14 - WINDOW + 1)


def test_collate_pads_agents(synthetic):
    samples = [synthetic[0], synthetic[len(synthetic) - 1]]
    batch = collate_samples(samples)
    a_max = max(s.box_labels.shape[0] for s in samples)
    assert batch.occ.shape == (2, WINDOW, 200, 200, 16)
    assert batch.boxes.shape == (2, WINDOW, a_max, 7) and batch.box_valid.shape == (2, WINDOW, a_max)
    for k, s in enumerate(samples):
        a = s.box_labels.shape[0]
        assert torch.equal(batch.box_labels[k, :a], s.box_labels)
        assert (batch.box_labels[k, a:] == -1).all() and not batch.box_valid[k, :, a:].any()
    assert batch.past_occ.shape[1] == 5 and batch.future_occ.shape[1] == 6
    assert batch.scene == [s.scene for s in samples]


@pytest.fixture(scope="module")
def world():
    return simulate_scene(scene_seed("test", 3), 40)


def test_agents_never_overlap_buildings(world):
    """No agent's box (nor the ego's) contains a manmade voxel of the static town."""
    checked = 0
    for t in range(0, len(world.ego_poses), 3):
        pose = world.ego_poses[t]
        static = render_static(world.static, world.network.warp, ego_xy_yaw(pose))
        boxes = world_to_ego(world.boxes_world[t], pose)
        ego = np.array([[0.0, 0.0, 0.6, C.EGO_LENGTH, C.EGO_WIDTH, 1.5, 0.0]])
        for box in np.concatenate([boxes, ego]):
            x, y, _, length, width, height, yaw = box
            if abs(x) > 38 or abs(y) > 38:
                continue
            xc, yc = C.voxel_centers(0), C.voxel_centers(1)
            dx, dy = xc[:, None] - x, yc[None, :] - y
            inside = (np.abs(np.cos(yaw) * dx + np.sin(yaw) * dy) <= length / 2) & (
                np.abs(-np.sin(yaw) * dx + np.cos(yaw) * dy) <= width / 2
            )
            column = static[inside][:, GROUND_Z + 1 : z_level(height)]
            assert not (column == C.MANMADE).any(), f"agent box {box} overlaps a building at frame {t}"
            checked += 1
    assert checked > 100


def test_ego_stays_on_the_road(synthetic, world):
    scenes = [synthetic.scenes.generate(k) for k in range(len(synthetic.scenes))]
    for scene in scenes:
        under_ego = scene.occ[:, 98:102, 99:101, GROUND_Z]  # 1.6 m x 0.8 m around the ego origin
        assert (under_ego == C.DRIVEABLE_SURFACE).all()
    for t in range(len(world.ego_poses)):
        static = render_static(world.static, world.network.warp, ego_xy_yaw(world.ego_poses[t]))
        assert (static[95:105, 98:102, GROUND_Z] == C.DRIVEABLE_SURFACE).all()


def _reprojection_agreement(prev: np.ndarray, nxt: np.ndarray, yaw: float, shift: np.ndarray) -> float:
    """Move frame-t ground labels by (rotation ``yaw``, translation ``shift``) into frame t+1; share that agree."""
    xc, yc = C.voxel_centers(0), C.voxel_centers(1)
    X, Y = np.meshgrid(xc, yc, indexing="ij")
    c, s = np.cos(yaw), np.sin(yaw)
    # point p_t in frame t is R^T (p_t - shift) in frame t+1 (shift, yaw: frame t+1 origin/heading in frame t)
    x1 = c * (X - shift[0]) + s * (Y - shift[1])
    y1 = -s * (X - shift[0]) + c * (Y - shift[1])
    i = np.floor((x1 + 40) / C.VOXEL_SIZE).astype(int)
    j = np.floor((y1 + 40) / C.VOXEL_SIZE).astype(int)
    ok = (i >= 0) & (i < 200) & (j >= 0) & (j < 200) & (prev != C.FREE)
    return float((prev[ok] == nxt[i[ok], j[ok]]).mean())


def test_actions_match_the_motion_of_the_static_world(synthetic):
    moved = 0
    for index in range(0, len(synthetic), 2):
        s = synthetic[index]
        poses = s.ego_poses.double().numpy()
        yaw = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
        actions = torch.cat([s.past_actions, s.future_actions]).double().numpy()
        for t in (PRESENT - 1, PRESENT + 2):
            # the action is in present coordinates; express it in frame t's coordinates
            rel_yaw = yaw[t] - yaw[PRESENT]
            c, si = np.cos(rel_yaw), np.sin(rel_yaw)
            shift = np.array([c * actions[t, 0] + si * actions[t, 1], -si * actions[t, 0] + c * actions[t, 1]])
            if np.linalg.norm(shift) < 1.5:
                continue
            prev = s.occ[t, :, :, GROUND_Z].numpy()
            nxt = s.occ[t + 1, :, :, GROUND_Z].numpy()
            good = _reprojection_agreement(prev, nxt, yaw[t + 1] - yaw[t], shift)
            still = _reprojection_agreement(prev, nxt, 0.0, np.zeros(2))
            wrong = _reprojection_agreement(prev, nxt, yaw[t + 1] - yaw[t], -shift)
            assert good > 0.93, good
            assert good > still + 0.02 and good > wrong + 0.02
            moved += 1
    assert moved >= 3


def test_constant_velocity_is_often_wrong():
    ds = SyntheticDriving("test", num_scenes=3, frames_per_scene=40, stride=3)
    errors = np.array([constant_velocity_error(ds[i]) for i in range(len(ds))])
    speeds = np.array([float(ds[i].future_actions.norm(dim=1).mean()) / C.FRAME_DT for i in range(len(ds))])
    assert np.mean(errors > 1.0) > 0.3, errors
    assert np.mean(speeds < 0.5) < 0.6  # not parked all the time
    assert speeds.max() > 6.0


def test_class_frequencies_look_like_occ3d():
    frames = SyntheticFrames("val", num_scenes=4, frames_per_scene=20)
    counts = np.zeros(18, dtype=np.int64)
    for i in range(0, len(frames), 2):
        counts += np.bincount(frames[i].numpy().reshape(-1), minlength=18)
    share = counts / counts.sum()
    assert share[C.FREE] > 0.85
    assert (counts[: C.FREE] > 0).all(), [C.CLASS_NAMES[i] for i in np.flatnonzero(counts[: C.FREE] == 0)]


def test_visibility_mask_hides_what_is_behind():
    scene = generate_scene(scene_seed("val", 5), 11)
    for occ, mask in zip(scene.occ, scene.mask_camera):
        assert 0.15 < mask.mean() < 0.98
        near, seen = occ[95:105, 95:105], mask[95:105, 95:105]
        top = 15 - np.argmax(near[..., ::-1] != C.FREE, axis=-1)  # the surface of each column around the ego
        ground = np.isin(np.take_along_axis(near, top[..., None], -1)[..., 0], GROUND_CLASSES)
        assert ground.mean() > 0.5 and np.take_along_axis(seen, top[..., None], -1)[..., 0][ground].all()  # is seen
        raised = near[..., GROUND_Z + 1] != C.FREE
        assert not seen[..., GROUND_Z][raised].any()  # the ground under a kerb or an agent is not
        assert mask[occ == C.DRIVEABLE_SURFACE].mean() > 0.4


def test_flips_are_consistent(synthetic):
    s = synthetic[1]
    for axis, k in (("x", 0), ("y", 1)):
        f = flip_sample(s, axis)
        assert torch.equal(f.occ, s.occ.flip(k + 1)) and torch.equal(f.mask_camera, s.mask_camera.flip(k + 1))
        assert torch.allclose(f.future_actions[:, k], -s.future_actions[:, k])
        assert torch.allclose(f.future_actions[:, 1 - k], s.future_actions[:, 1 - k])
        past, fut = actions_from_poses(f.ego_poses.double().numpy())
        np.testing.assert_allclose(fut, f.future_actions.numpy(), atol=1e-3)
        np.testing.assert_allclose(past, f.past_actions.numpy(), atol=1e-3)
        back = flip_sample(f, axis)
        assert torch.equal(back.occ, s.occ)
        assert torch.allclose(back.boxes, s.boxes, atol=1e-5)
        # the agent under each present-frame box centre keeps its class after the flip
        valid = f.box_valid[PRESENT]
        for box, label in zip(f.boxes[PRESENT][valid], f.box_labels[valid]):
            i = int((box[0] + 40) // C.VOXEL_SIZE)
            j = int((box[1] + 40) // C.VOXEL_SIZE)
            if 0 <= i < 200 and 0 <= j < 200:
                assert int(label) in f.occ[PRESENT, i, j].tolist()
        # yaw follows the mirrored heading
        yaw_s, yaw_f = s.boxes[PRESENT, :, 6][s.box_valid[PRESENT]], f.boxes[PRESENT, :, 6][valid]
        heading = torch.stack([torch.cos(yaw_s), torch.sin(yaw_s)], -1)
        heading[:, k] = -heading[:, k]
        assert torch.allclose(torch.stack([torch.cos(yaw_f), torch.sin(yaw_f)], -1), heading, atol=1e-5)


def test_frames_dataset(synthetic):
    frames = SyntheticFrames(synthetic.scenes.split, synthetic.scenes.num_scenes, synthetic.scenes.frames_per_scene)
    assert len(frames) == 2 * 14
    vol = frames[PRESENT]
    assert vol.shape == (200, 200, 16) and vol.dtype == torch.uint8
    assert torch.equal(vol, synthetic[0].occ[PRESENT])


@pytest.fixture(scope="module")
def layout_frames():
    """Every 4th frame of three test scenes, ``[N, 200, 200, 16]``."""
    return np.concatenate([generate_scene(scene_seed("test", k), 40).occ[::4] for k in range(3)])


def test_ground_is_level_zero_wherever_there_is_road(layout_frames):
    road = layout_frames == C.DRIVEABLE_SURFACE
    assert road[..., GROUND_Z].sum() > 5000 * len(layout_frames)
    assert not road[..., GROUND_Z + 1 :].any()
    ground = np.isin(layout_frames, GROUND_CLASSES)
    assert not ground[..., GROUND_Z + 3 :].any()  # kerbs and banks rise two levels at most


def test_nothing_floats_under_the_ground(layout_frames):
    """No free voxel under a ground voxel: raised ground is filled down to level 0."""
    for z in range(GROUND_Z + 1, GROUND_Z + 3):
        ground = np.isin(layout_frames[..., z], GROUND_CLASSES)
        assert ground.any()
        assert not (layout_frames[..., : z][ground] == C.FREE).any()


def test_agents_rest_on_the_ground(layout_frames):
    agent = np.isin(layout_frames, C.AGENT_CLASSES)
    columns = agent.any(-1)
    lowest = np.argmax(agent, axis=-1)[columns]
    assert (lowest == GROUND_Z + 1).all()  # the bottom of every agent is the level above the ground
    under = layout_frames[..., GROUND_Z][columns]
    assert np.mean(under != C.FREE) > 0.99


def test_trees_have_trunks_and_crowns_at_occ3d_heights(layout_frames):
    veg = layout_frames == C.VEGETATION
    trunk = veg[..., GROUND_Z : GROUND_Z + 6].all(-1) & veg[..., 8:11].any(-1)  # from the ground into a crown
    assert trunk.sum() > 20
    per_z = veg.sum(axis=(0, 1, 2))
    assert per_z[7:11].mean() > 2 * per_z[GROUND_Z : GROUND_Z + 3].mean() > 0  # crowns above trunks and bushes
    assert per_z[15] > 0  # big trees reach past the grid top


def test_every_agent_class_turns_up_within_a_few_scenes(layout_frames):
    present = set(np.unique(layout_frames).tolist())
    missing = [C.CLASS_NAMES[c] for c in range(C.FREE) if c not in present]
    assert not missing, missing


def test_free_share_is_like_occ3d(layout_frames):
    assert 0.92 < (layout_frames == C.FREE).mean() < 0.96
