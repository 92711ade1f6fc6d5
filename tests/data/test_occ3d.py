import pickle
import shutil

import numpy as np
import pytest
import torch

from t3fast.data import classes as C
from t3fast.data.occ3d import Occ3DFormatError, Occ3DNuScenes, read_infos, read_labels
from t3fast.data.sample import PRESENT


def test_round_trip_export_equals_synthetic(synthetic, exported):
    root, info = exported
    loaded = Occ3DNuScenes(root, info)
    assert len(loaded) == len(synthetic)
    for i in range(len(synthetic)):
        a, b = synthetic[i], loaded[i]
        assert (a.scene, a.start) == (b.scene, b.start)
        assert torch.equal(a.occ, b.occ) and torch.equal(a.mask_camera, b.mask_camera)
        assert torch.allclose(a.past_actions, b.past_actions, atol=1e-4)
        assert torch.allclose(a.future_actions, b.future_actions, atol=1e-4)
        assert torch.equal(a.box_labels, b.box_labels) and torch.equal(a.box_valid, b.box_valid)
        assert torch.allclose(a.boxes, b.boxes, atol=1e-3)
        assert torch.allclose(a.ego_poses, b.ego_poses, atol=1e-3)
        assert torch.equal(a.command, b.command)  # exported as gt_ego_fut_cmd and read back


def test_without_instance_tokens_future_boxes_come_from_agent_trajectories(synthetic, exported, tmp_path):
    root, info = exported
    with open(info, "rb") as f:
        data = pickle.load(f)
    for frames in data["infos"].values():
        for frame in frames:
            del frame["instance_tokens"]
    stripped = tmp_path / "no_ids.pkl"
    with open(stripped, "wb") as f:
        pickle.dump(data, f)
    a, b = synthetic[0], Occ3DNuScenes(root, stripped)[0]
    present = a.box_valid[PRESENT]
    assert b.box_labels.shape[0] == int(present.sum())
    assert torch.allclose(b.boxes[PRESENT, :, :6], a.boxes[PRESENT][present][:, :6], atol=1e-3)
    both = b.box_valid[PRESENT + 3] & a.box_valid[PRESENT + 3][present]
    assert both.any()
    assert torch.allclose(b.boxes[PRESENT + 3][both][:, :2], a.boxes[PRESENT + 3][present][both][:, :2], atol=1e-3)


def _labels_file(tmp_path, **overrides):
    arrays = {
        "semantics": np.full(C.GRID_SHAPE, C.FREE, np.uint8),
        "mask_lidar": np.ones(C.GRID_SHAPE, np.uint8),
        "mask_camera": np.ones(C.GRID_SHAPE, np.uint8),
    }
    arrays.update(overrides)
    path = tmp_path / "gts" / "scene-0001" / "abc" / "labels.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


def test_read_labels_accepts_a_good_file(tmp_path):
    sem = np.full(C.GRID_SHAPE, C.FREE, np.uint8)
    sem[0, 0, 0] = C.IGNORE
    out = read_labels(_labels_file(tmp_path, semantics=sem))
    assert out["semantics"].dtype == np.uint8 and out["mask_camera"].dtype == bool


@pytest.mark.parametrize(
    "overrides, problem",
    [
        (
            {"semantics": np.zeros((200, 200, 15), np.uint8)},
            "'semantics' has shape (200, 200, 15), expected (200, 200, 16)",
        ),
        ({"mask_camera": np.zeros((200, 200), np.uint8)}, "'mask_camera' has shape (200, 200)"),
        ({"semantics": np.full(C.GRID_SHAPE, 18, np.uint8)}, "labels outside 0..17 and 255: [18]"),
        ({"mask_camera": None}, "missing array 'mask_camera'"),
        ({"semantics": np.zeros(C.GRID_SHAPE, np.float32)}, "dtype float32"),
        ({"mask_lidar": np.full(C.GRID_SHAPE, 3, np.uint8)}, "'mask_lidar' has values other than 0 and 1"),
    ],
)
def test_bad_label_files_name_file_and_problem(tmp_path, overrides, problem):
    path = _labels_file(tmp_path, **overrides)
    with pytest.raises(Occ3DFormatError) as err:
        read_labels(path)
    assert str(path) in str(err.value) and problem in str(err.value)


def test_missing_and_corrupt_label_files(tmp_path):
    missing = tmp_path / "gts" / "s" / "t" / "labels.npz"
    with pytest.raises(Occ3DFormatError, match="file not found") as err:
        read_labels(missing)
    assert str(missing) in str(err.value)
    corrupt = _labels_file(tmp_path)
    corrupt.write_bytes(corrupt.read_bytes()[:1000])
    with pytest.raises(Occ3DFormatError, match="not a readable .npz") as err:
        read_labels(corrupt)
    assert str(corrupt) in str(err.value)
    assert issubclass(Occ3DFormatError, ValueError)


def test_dataset_reports_the_bad_frame(exported, tmp_path):
    root, info = exported
    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    loaded = Occ3DNuScenes(copy, info)
    scene, start = loaded.index[0]
    token = loaded.infos[scene][start + 2]["token"]
    victim = loaded.label_path(scene, token)
    victim.unlink()
    with pytest.raises(Occ3DFormatError, match="file not found") as err:
        loaded[0]
    assert str(victim) in str(err.value)


def test_bad_info_pickles(tmp_path):
    with pytest.raises(Occ3DFormatError, match="file not found"):
        read_infos(tmp_path / "nope.pkl")
    junk = tmp_path / "junk.pkl"
    junk.write_bytes(b"not a pickle")
    with pytest.raises(Occ3DFormatError, match="not a readable pickle") as err:
        read_infos(junk)
    assert str(junk) in str(err.value)
    wrong = tmp_path / "wrong.pkl"
    wrong.write_bytes(pickle.dumps({"data_list": []}))
    with pytest.raises(Occ3DFormatError, match="key 'infos'"):
        read_infos(wrong)
    keyless = tmp_path / "keyless.pkl"
    keyless.write_bytes(pickle.dumps({"infos": {"scene-1": [{"token": "a", "ego2global_translation": [0, 0, 0]}]}}))
    with pytest.raises(Occ3DFormatError, match="no 'ego2global_rotation'"):
        read_infos(keyless)


def test_the_info_files_route_command_is_read_not_derived(exported, tmp_path):
    from t3fast.data.route import LEFT, RIGHT

    root, info = exported
    with open(info, "rb") as f:
        data = pickle.load(f)
    scene = next(iter(data["infos"]))
    derived = Occ3DNuScenes(root, info)[0].command
    assert data["infos"][scene][PRESENT]["gt_ego_fut_cmd"].tolist() == np.eye(3)[int(derived)].tolist()
    other = LEFT if int(derived) != LEFT else RIGHT
    data["infos"][scene][PRESENT]["gt_ego_fut_cmd"] = np.eye(3)[other]
    changed = tmp_path / "command.pkl"
    changed.write_bytes(pickle.dumps(data))
    assert int(Occ3DNuScenes(root, changed)[0].command) == other
    for frame in data["infos"][scene]:  # without the key: derived from the ego's future
        del frame["gt_ego_fut_cmd"]
    changed.write_bytes(pickle.dumps(data))
    assert torch.equal(Occ3DNuScenes(root, changed)[0].command, derived)


def test_bad_trajectory_shape(exported, tmp_path):
    root, info = exported
    with open(info, "rb") as f:
        data = pickle.load(f)
    scene = next(iter(data["infos"]))
    data["infos"][scene][PRESENT]["gt_ego_fut_trajs"] = np.zeros((5, 2))
    bad = tmp_path / "bad_traj.pkl"
    bad.write_bytes(pickle.dumps(data))
    with pytest.raises(Occ3DFormatError, match=r"'gt_ego_fut_trajs' has shape \(5, 2\)"):
        Occ3DNuScenes(root, bad)[0]


def test_lidar_frame_infos_are_moved_to_ego(synthetic, exported, tmp_path):
    """Boxes and trajectories given in a LiDAR frame rotated 90 degrees (nuScenes) load identically."""
    root, info = exported
    with open(info, "rb") as f:
        data = pickle.load(f)
    quarter = [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]  # lidar -> ego: +90 deg about z
    for frames in data["infos"].values():
        for fr in frames:
            fr["lidar2ego_rotation"] = quarter
            fr["lidar2ego_translation"] = [0.0, 0.0, 0.0]
            boxes = fr["gt_boxes"].copy()
            boxes[:, 0], boxes[:, 1] = fr["gt_boxes"][:, 1], -fr["gt_boxes"][:, 0]
            boxes[:, 6] = fr["gt_boxes"][:, 6] - np.pi / 2
            fr["gt_boxes"] = boxes
            traj = fr["gt_ego_fut_trajs"]
            fr["gt_ego_fut_trajs"] = np.stack([traj[:, 1], -traj[:, 0]], -1)
    lidar = tmp_path / "lidar.pkl"
    lidar.write_bytes(pickle.dumps(data))
    a, b = synthetic[0], Occ3DNuScenes(root, lidar)[0]
    assert torch.allclose(a.future_actions, b.future_actions, atol=1e-4)
    assert torch.allclose(a.boxes[..., :6], b.boxes[..., :6], atol=1e-3)
    assert torch.allclose(torch.cos(a.boxes[..., 6]), torch.cos(b.boxes[..., 6]), atol=1e-4)
