"""``t3fast view``: a synthetic scene, an Occ3D folder, and a shipped model's forecast, written as
pages whose embedded labels are exactly the window's; bad arguments name the problem."""

from __future__ import annotations

import os

import numpy as np

from t3fast.commands.main import main
from t3fast.data.export import export_synthetic
from t3fast.data.synthetic import SyntheticDriving
from t3fast.viz.viewer import read_viewer_data


def test_view_a_synthetic_scene(tmp_path):
    out = tmp_path / "scene.html"
    assert main(["view", "--synthetic", "val:1", "--start", "3", "--out", str(out)]) == 0
    data = read_viewer_data(out)
    window = SyntheticDriving("val", 2, stride=1)[30 + 3]  # scene 1 (30 windows per scene), frame 3
    assert window.scene.endswith("00001") and window.start == 3
    np.testing.assert_array_equal(data["sequences"]["scene"], window.occ.numpy())
    np.testing.assert_array_equal(data["masks"], window.mask_camera.numpy())


def test_view_an_occ3d_folder_matches_its_labels(tmp_path):
    root = tmp_path / "occ3d"
    export_synthetic(root, "val", 1, 11, progress=False)
    out = tmp_path / "view.html"
    assert main(["view", "--data", str(root), "--out", str(out)]) == 0
    expected = SyntheticDriving("val", 1, 11)[0].occ.numpy()
    np.testing.assert_array_equal(read_viewer_data(out)["sequences"]["scene"], expected)


def test_view_a_forecast_of_a_shipped_model(tmp_path):
    out = tmp_path / "forecast.html"
    assert main(["view", "--synthetic", "test:0", "--ckpt", "wm-small", "--out", str(out)]) == 0
    data = read_viewer_data(out)
    window = SyntheticDriving("test", 1, stride=1)[0]
    assert data["sequences"]["predicted"].shape == (6, 200, 200, 16)
    np.testing.assert_array_equal(data["sequences"]["truth"], window.future_occ.numpy())
    assert [t["name"] for t in data["trajectories"]] == ["true trajectory", "plan"]


def test_bad_arguments_name_the_problem(tmp_path, capsys):
    assert main(["view", "--synthetic", "test", "--out", str(tmp_path / "a.html")]) == 2
    assert "expected SPLIT:SCENE" in capsys.readouterr().err
    assert main(["view", "--synthetic", "test:0", "--start", "35", "--out", str(tmp_path / "a.html")]) == 2
    assert "windows start at 0..29" in capsys.readouterr().err
    assert main(["view", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "a.html")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert main(["view", "--synthetic", "test:0", "--ckpt", "wm-huge", "--out", str(tmp_path / "a.html")]) == 1
    assert "neither a checkpoint file nor a shipped model" in capsys.readouterr().err


def test_view_does_not_write_through_a_link_or_into_a_special_file(tmp_path, capsys):
    target = tmp_path / "elsewhere.html"
    target.write_text("someone else's page")
    link = tmp_path / "view.html"
    link.symlink_to(target)
    assert main(["view", "--synthetic", "test:0", "--out", str(link)]) == 2
    err = capsys.readouterr().err
    assert err == (f"t3fast view: {link} is a symbolic link: not writing through it "
                   "(remove it or choose another --out)\n")
    assert target.read_text() == "someone else's page"
    fifo = tmp_path / "fifo.html"
    os.mkfifo(fifo)  # writing would block until something reads it
    assert main(["view", "--synthetic", "test:0", "--out", str(fifo)]) == 2
    assert capsys.readouterr().err == f"t3fast view: {fifo} is a FIFO, not a regular file: not writing over it\n"
