"""Info files are untrusted: no code runs from them, their names never leave the data or
output folder, and bad poses are refused with the frame named."""

from __future__ import annotations

import math
import os
import pickle

import numpy as np
import pytest
import torch

from t3fast.commands.main import main
from t3fast.data.occ3d import Occ3DNuScenes, read_infos
from t3fast.data.occ3d_frames import Occ3DFrames
from t3fast.data.safe_pickle import load_restricted
from t3fast.errors import DataFormatError
from t3fast.paths import check_name, inside


class ShellPayload:
    """Unpickling this runs a shell command that creates ``path``."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return os.system, (f"touch {self.path}",)


def write_info(path, data) -> None:
    path.write_bytes(pickle.dumps(data))


@pytest.fixture
def infos(exported):
    """A fresh copy of the exported scenes' info dict, to corrupt."""
    with open(exported[1], "rb") as f:
        return pickle.load(f)


def test_hostile_pickle_runs_nothing(tmp_path, capsys):
    live = tmp_path / "live"
    pickle.loads(pickle.dumps(ShellPayload(live)))  # the payload does run under plain pickle
    assert live.exists()

    marker = tmp_path / "pwned"
    data = tmp_path / "data"
    data.mkdir()
    write_info(data / "infos.pkl", {"infos": {"scene-1": [ShellPayload(marker)]}})
    with pytest.raises(DataFormatError, match=r"refusing to load posix\.system|refusing to load os\.system"):
        read_infos(data / "infos.pkl")
    assert main(["forecast", "--data", str(data), "--ckpt", str(tmp_path / "none.pt"), "--out",
                 str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("t3fast forecast: ") and "refusing to load" in err and err.count("\n") == 1
    assert not marker.exists() and not (tmp_path / "out").exists()


def test_restricted_loader_reads_what_info_files_hold(exported, tmp_path):
    with open(exported[1], "rb") as f:
        expected = pickle.load(f)
    loaded = load_restricted(exported[1])
    scene = next(iter(expected["infos"]))
    for a, b in zip(expected["infos"][scene], loaded["infos"][scene], strict=True):
        assert a.keys() == b.keys()
        for key in a:
            assert np.array_equal(np.asarray(a[key]), np.asarray(b[key])), key
    plain = {"s": "x", "i": 3, "f": 1.5, "b": True, "n": None, "t": (1, 2), "l": [b"raw"],
             "a": np.arange(4, dtype=np.float32), "o": np.array(["car", 1], dtype=object), "sc": np.float64(2.0)}
    for protocol in range(pickle.HIGHEST_PROTOCOL + 1):  # old files (protocol 2) spell bytes via _codecs
        (tmp_path / "p.pkl").write_bytes(pickle.dumps(plain, protocol=protocol))
        back = load_restricted(tmp_path / "p.pkl")
        assert back.keys() == plain.keys() and np.array_equal(back["a"], plain["a"]) and back["t"] == (1, 2)


@pytest.mark.parametrize("name", ["..", "../../escaped_scene", "/tmp/abs", "a/b", "a\\b", "", "."])
def test_unsafe_names_are_refused(name):
    with pytest.raises(DataFormatError, match="not a plain folder name"):
        check_name(name, "scene name")


def test_safe_names_pass():
    for name in ["scene-0001", "e93e98b63d3b40209056d129dc53ceee", "a..b"]:
        assert check_name(name, "token") == name


def test_inside_refuses_symlinks_out(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "link").symlink_to(tmp_path)
    assert inside(tmp_path / "out", "a", "b") == tmp_path / "out" / "a" / "b"
    with pytest.raises(DataFormatError, match="outside"):
        inside(tmp_path / "out", "link", "x")


@pytest.mark.parametrize("where", ["scene", "token", "absolute token"])
def test_traversal_names_write_nothing(exported, infos, tmp_path, where, capsys):
    root, _ = exported
    scene = next(iter(infos["infos"]))
    if where == "scene":
        infos["infos"]["../../escaped_scene"] = infos["infos"].pop(scene)
    else:
        token = str(tmp_path / "abs") if where == "absolute token" else "../../escaped"
        infos["infos"][scene][5]["token"] = token
    write_info(tmp_path / "bad.pkl", infos)
    out = tmp_path / "a" / "b" / "out"
    assert main(["forecast", "--data", str(root), "--info", str(tmp_path / "bad.pkl"), "--ckpt",
                 str(tmp_path / "none.pt"), "--out", str(out)]) == 1
    assert "not a plain folder name" in capsys.readouterr().err
    written = [p for p in tmp_path.rglob("*") if p.name in ("labels.npz", "trajectory.json")]
    assert written == []


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("ego2global_rotation", [0.0, 0.0, 0.0, 0.0], "not a unit quaternion"),
        ("ego2global_rotation", [2.0, 0.0, 0.0, 0.0], "not a unit quaternion"),
        ("ego2global_translation", [0.0, math.nan, 0.0], "non-finite"),
        ("ego2global_translation", [0.0, 0.0], "shape"),
        ("lidar2ego_rotation", [1.0, 0.0, math.inf, 0.0], "non-finite"),
    ],
)
def test_bad_poses_name_the_frame(infos, tmp_path, key, value, message):
    scene = next(iter(infos["infos"]))
    infos["infos"][scene][3][key] = value
    write_info(tmp_path / "bad.pkl", infos)
    token = infos["infos"][scene][3]["token"]
    with pytest.raises(DataFormatError, match=f"scene {scene!r} frame 3 \\(token {token!r}\\): '{key}'.*{message}"):
        read_infos(tmp_path / "bad.pkl")


def test_structure_errors(infos, tmp_path):
    scene = next(iter(infos["infos"]))
    frames = infos["infos"][scene]
    cases = {
        "must be a list of frames, got str": {"infos": {scene: "frames"}},
        "frame 0 must be a dict, got int": {"infos": {scene: [1]}},
        "token 'x' appears twice": {"infos": {scene: [{**frames[0], "token": "x"}, {**frames[1], "token": "x"}]}},
        "token must be a string, got int": {"infos": {scene: [{**frames[0], "token": 7}]}},
    }
    for message, data in cases.items():
        write_info(tmp_path / "bad.pkl", data)
        with pytest.raises(DataFormatError, match=message):
            read_infos(tmp_path / "bad.pkl")


def test_forecast_refuses_bad_poses_and_nothing_to_do(exported, infos, tmp_path, capsys):
    root, _ = exported
    out = tmp_path / "out"
    forecast = ["forecast", "--data", str(root), "--info", str(tmp_path / "bad.pkl"), "--ckpt",
                str(tmp_path / "none.pt"), "--out", str(out)]
    scene = next(iter(infos["infos"]))
    rotation = infos["infos"][scene][2]["ego2global_rotation"]
    infos["infos"][scene][2]["ego2global_rotation"] = [0.0, 0.0, 0.0, 0.0]
    write_info(tmp_path / "bad.pkl", infos)
    assert main(forecast) == 1
    err = capsys.readouterr().err
    token = infos["infos"][scene][2]["token"]
    assert err == (f"t3fast forecast: {tmp_path / 'bad.pkl'}: scene {scene!r} frame 2 (token {token!r}): "
                   "'ego2global_rotation' is not a unit quaternion (norm 0)\n")

    infos["infos"][scene][2]["ego2global_rotation"] = rotation
    infos["infos"] = {name: frames[:10] for name, frames in infos["infos"].items()}  # one frame short of a window
    write_info(tmp_path / "bad.pkl", infos)
    assert main(forecast) == 1
    assert "nothing to forecast" in capsys.readouterr().err
    assert not out.exists()


def _boxes(frame) -> int:
    return len(frame["gt_boxes"])


#: (field, a function of the frame giving the bad value, what the message must say)
BAD_FIELDS = {
    "ego masks a string": ("gt_ego_fut_masks", lambda f: "xx", "must hold numbers, got str 'xx'"),
    "ego masks too short": ("gt_ego_fut_masks", lambda f: np.ones(5), "has shape (5,), expected (6,)"),
    "ego trajectory 3 columns": ("gt_ego_fut_trajs", lambda f: np.zeros((6, 3)), "has shape (6, 3), expected (6, 2)"),
    "ego trajectory ragged": ("gt_ego_fut_trajs", lambda f: [[0.0, 1.0], [2.0]], "is not an array of numbers"),
    "command two-hot": ("gt_ego_fut_cmd", lambda f: [1.0, 1.0, 0.0],
                        "must be a one-hot of 3 (turn right, turn left, go straight), got [1.0, 1.0, 0.0]"),
    "command of 4": ("gt_ego_fut_cmd", lambda f: np.eye(4)[0], "must be a one-hot of 3"),
    "names an int": ("gt_names", lambda f: 5, "must be a list or array of strings, got int 5"),
    "names not strings": ("gt_names", lambda f: np.arange(_boxes(f)), "must hold strings, got int 0"),
    "names one short": ("gt_names", lambda f: f["gt_names"][:-1],
                        "has {n1} entries but 'gt_boxes' has {n} boxes"),
    "boxes 6 columns": ("gt_boxes", lambda f: f["gt_boxes"][:, :6], "has shape ({n}, 6), expected (N, 7)"),
    "boxes flat": ("gt_boxes", lambda f: f["gt_boxes"].reshape(-1), "has shape ({n7},), expected (N, 7)"),
    "boxes strings": ("gt_boxes", lambda f: f["gt_boxes"].astype(str), "must hold numbers, got ndarray of <U"),
    "tokens one extra": ("instance_tokens", lambda f: np.append(f["instance_tokens"], "x"),
                         "has {n+1} entries but 'gt_boxes' has {n} boxes"),
    "tokens repeated": ("instance_tokens", lambda f: np.array([f["instance_tokens"][0]] * _boxes(f)),
                        "has {tok0!r} twice"),
    "tokens 2-D": ("instance_tokens", lambda f: f["instance_tokens"][:, None], "has shape ({n}, 1), expected (N,)"),
    "tokens floats": ("instance_tokens", lambda f: [0.5] * _boxes(f), "must hold strings, got float 0.5"),
    "agent trajectories one row short": ("gt_agent_fut_trajs", lambda f: f["gt_agent_fut_trajs"][:-1],
                                         "has {n1} rows (shape ({n1}, 12)) but 'gt_boxes' has {n} boxes"),
    "agent trajectories odd columns": ("gt_agent_fut_trajs", lambda f: f["gt_agent_fut_trajs"][:, :11],
                                       "has shape ({n}, 11), expected (N, 2 * steps)"),
    "agent masks for other steps": ("gt_agent_fut_masks", lambda f: f["gt_agent_fut_masks"][:, :5],
                                    "has shape ({n}, 5), expected (N, 6)"),
    "agent masks a dict": ("gt_agent_fut_masks", lambda f: {"a": 1}, "must hold numbers, got dict"),
}

#: values that are not finite once they are float32, as every sample is
NON_FINITE = {
    "NaN box": ("gt_boxes", lambda f: _with(f["gt_boxes"], (1, 3), math.nan), "first at index (1, 3): nan"),
    "inf agent trajectory": ("gt_agent_fut_trajs", lambda f: _with(f["gt_agent_fut_trajs"], (0, 5), -math.inf),
                             "first at index (0, 5): -inf"),
    "huge ego trajectory": ("gt_ego_fut_trajs", lambda f: _with(f["gt_ego_fut_trajs"], (2, 0), 1e39),
                            "first at index (2, 0): 1e+39"),
    "NaN ego mask": ("gt_ego_fut_masks", lambda f: _with(f["gt_ego_fut_masks"], (0,), math.nan), "nan"),
    "translation 1e300": ("ego2global_translation", lambda f: [0.0, 1e300, 0.0], "first at index (1,): 1e+300"),
    "lidar translation 1e300": ("lidar2ego_translation", lambda f: [1e300, 0.0, 0.0], "1e+300"),
}


def _with(array, index, value):
    out = np.array(array, dtype=np.float64)
    out[index] = value
    return out


@pytest.mark.parametrize("case", sorted(BAD_FIELDS) + sorted(NON_FINITE))
def test_bad_info_fields_name_file_scene_frame_and_field(infos, tmp_path, case):
    key, make, expected = {**BAD_FIELDS, **NON_FINITE}[case]
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][3]
    n = _boxes(frame)
    assert n >= 2
    frame[key] = make(frame)
    if key.startswith("lidar2ego"):
        frame["lidar2ego_rotation"] = [1.0, 0.0, 0.0, 0.0]
    expected = expected.format(n=n, n1=n - 1, n7=7 * n, tok0=str(frame.get("instance_tokens", ["?"])[0]),
                               **{"n+1": n + 1})
    write_info(tmp_path / "bad.pkl", infos)
    with pytest.raises(DataFormatError) as err:
        read_infos(tmp_path / "bad.pkl")
    where = f"{tmp_path / 'bad.pkl'}: scene {scene!r} frame 3 (token {frame['token']!r}): {key!r} "
    assert str(err.value).startswith(where), str(err.value)
    assert expected in str(err.value)
    if case in NON_FINITE:
        assert "non-finite value" in str(err.value) and "in float32" in str(err.value)


def test_float32_finite_but_overflowing_poses_are_refused_per_window(exported, infos, tmp_path):
    """Each translation is finite in float32, but the step between two frames is not."""
    root, _ = exported
    scene = next(iter(infos["infos"]))
    infos["infos"][scene][1]["ego2global_translation"] = [3e38, 0.0, 0.0]
    infos["infos"][scene][2]["ego2global_translation"] = [-3e38, 0.0, 0.0]
    write_info(tmp_path / "bad.pkl", infos)
    dataset = Occ3DNuScenes(root, tmp_path / "bad.pkl")
    with pytest.raises(DataFormatError, match=rf"scene {scene!r} frames 0\.\.10 .*past_actions are not finite"):
        dataset[0]


def test_cli_reports_a_bad_field_in_one_line(exported, infos, tmp_path, capsys):
    root, _ = exported
    scene = next(iter(infos["infos"]))
    infos["infos"][scene][0]["gt_boxes"] = _with(infos["infos"][scene][0]["gt_boxes"], (0, 0), math.nan)
    write_info(tmp_path / "bad.pkl", infos)
    for argv in (["data", "render", "--root", str(root), "--info", str(tmp_path / "bad.pkl"), "--out",
                  str(tmp_path / "r.png")],
                 ["view", "--data", str(root), "--info", str(tmp_path / "bad.pkl"), "--out", str(tmp_path / "v.html")]):
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(tmp_path / "bad.pkl") in err and f"scene {scene!r} frame 0 (token" in err
        assert "'gt_boxes' has 1 non-finite value in float32 (first at index (0, 0): nan)" in err
    assert not (tmp_path / "r.png").exists() and not (tmp_path / "v.html").exists()
    with pytest.raises(DataFormatError, match="'gt_boxes' has 1 non-finite"):
        Occ3DFrames(root, tmp_path / "bad.pkl")


def test_frames_without_boxes_or_with_empty_arrays_load(exported, infos, tmp_path):
    root, _ = exported
    scene = next(iter(infos["infos"]))
    for frame in infos["infos"][scene]:
        for key in ("gt_boxes", "gt_names", "instance_tokens", "gt_agent_fut_trajs", "gt_agent_fut_masks"):
            frame[key] = np.array([])
    infos["infos"][scene][1] = {k: v for k, v in infos["infos"][scene][1].items() if not k.startswith("gt_")}
    write_info(tmp_path / "empty.pkl", infos)
    sample = Occ3DNuScenes(root, tmp_path / "empty.pkl")[0]
    assert sample.boxes.shape[1] == 0 and torch.isfinite(sample.future_actions).all()
