"""Info files are untrusted: no code runs from them, their names never leave the data or
output folder, and bad poses are refused with the frame named."""

from __future__ import annotations

import math
import os
import pickle

import numpy as np
import pytest

from t3fast.commands.main import main
from t3fast.data.occ3d import read_infos
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
    with pytest.raises(DataFormatError, match=f"scene {scene!r} frame 3: '{key}'.*{message}"):
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
    assert err == (f"t3fast forecast: {tmp_path / 'bad.pkl'}: scene {scene!r} frame 2: "
                   "'ego2global_rotation' is not a unit quaternion (norm 0)\n")

    infos["infos"][scene][2]["ego2global_rotation"] = rotation
    infos["infos"] = {name: frames[:10] for name, frames in infos["infos"].items()}  # one frame short of a window
    write_info(tmp_path / "bad.pkl", infos)
    assert main(forecast) == 1
    assert "nothing to forecast" in capsys.readouterr().err
    assert not out.exists()
