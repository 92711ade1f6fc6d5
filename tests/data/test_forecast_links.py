"""``forecast`` writes only inside ``--out``: a symbolic link left anywhere in an earlier output
(a frame folder, a file, the scene folder) is refused before the model runs, not written through."""

from __future__ import annotations

import pytest

import t3fast.pretrained
from t3fast.commands.main import main
from t3fast.data.occ3d import Occ3DNuScenes
from t3fast.data.sample import PRESENT

SHIPPED_WM = "t3fast/checkpoints/wm-small.pt"


def first_window(root, info) -> tuple[str, str]:
    dataset = Occ3DNuScenes(root, info, stride=8)
    scene, start = dataset.index[0]
    return scene, dataset.infos[scene][start + PRESENT]["token"]


@pytest.mark.parametrize("link", ["future_1", "future_6/labels.npz", "trajectory.json", "forecast.gif",
                                  "forecast.html"])
def test_a_link_inside_out_is_refused_before_the_model_runs(exported, tmp_path, capsys, monkeypatch, link):
    root, info = exported
    scene, token = first_window(root, info)
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / scene / token / link).parent.mkdir(parents=True)
    target = elsewhere if link == "future_1" else elsewhere / "victim"
    (out / scene / token / link).symlink_to(target)

    def refuse(*args, **kwargs):
        raise AssertionError("loaded the model before checking the output paths")

    monkeypatch.setattr(t3fast.pretrained, "load_world_model", refuse)
    argv = ["forecast", "--data", str(root), "--info", str(info), "--ckpt", SHIPPED_WM, "--out", str(out),
            "--stride", "8", "--pictures", "1"]
    assert main(argv) == 2
    assert capsys.readouterr().err == (
        f"t3fast forecast: {out / scene / token / link} is a symbolic link: not writing through it "
        "(remove it or choose another --out)\n"
    )
    assert list(elsewhere.iterdir()) == []
    assert [p for p in out.rglob("*") if p.is_file()] == []


def test_a_linked_scene_folder_is_refused_even_inside_out(exported, tmp_path, capsys, monkeypatch):
    root, info = exported
    scene, _ = first_window(root, info)
    out = tmp_path / "out"
    (out / "real").mkdir(parents=True)
    (out / scene).symlink_to(out / "real")
    monkeypatch.setattr(t3fast.pretrained, "load_world_model", lambda *a, **k: pytest.fail("model loaded"))
    argv = ["forecast", "--data", str(root), "--info", str(info), "--ckpt", SHIPPED_WM, "--out", str(out),
            "--stride", "8", "--pictures", "0"]
    assert main(argv) == 2
    assert f"{out / scene} is a symbolic link" in capsys.readouterr().err
    assert list((out / "real").iterdir()) == []

