import numpy as np
import pytest
from PIL import Image

from t3fast.commands.main import main
from t3fast.data import classes as C
from t3fast.viz.bev import bev_colours, bev_image, render_sample


def test_bev_takes_the_highest_occupied_voxel():
    occ = np.full(C.GRID_SHAPE, C.FREE, np.uint8)
    occ[:, :, 1] = C.DRIVEABLE_SURFACE
    occ[10, 20, 2:6] = C.CAR
    occ[10, 20, 9] = C.VEGETATION
    occ[11, 20, 1] = C.IGNORE
    rgb = bev_colours(occ)
    assert rgb.shape == (200, 200, 3)
    assert tuple(rgb[10, 20]) == tuple(C.PALETTE[C.VEGETATION])
    assert tuple(rgb[0, 0]) == tuple(C.PALETTE[C.DRIVEABLE_SURFACE])
    image = bev_image(occ, scale=2)
    assert image.size == (400, 400)
    # x forward is up, y left is left: voxel (10, 20) sits near the bottom, towards the right
    row, col = (199 - 10) * 2, (199 - 20) * 2
    assert image.getpixel((col, row)) == tuple(int(c) for c in C.PALETTE[C.VEGETATION])


def test_render_sample_strip(synthetic):
    strip = render_sample(synthetic[0], frames=[0, 4, 10], scale=1)
    assert strip.size == (3 * 200 + 2 * 4, 200)


def test_cli_export_stats_render(tmp_path, capsys):
    out = tmp_path / "exp"
    args = ["data", "export-synthetic", "--out", str(out), "--scenes", "1", "--frames", "12", "--split", "test"]
    assert main(args) == 0
    info = out / "synthetic_infos_test.pkl"
    assert info.is_file() and len(list((out / "gts").glob("*/*/labels.npz"))) == 12
    assert main(["data", "stats", "--root", str(out), "--info", str(info), "--stride", "1"]) == 0
    text = capsys.readouterr().out
    assert "driveable_surface" in text and "constant-velocity" in text
    png = tmp_path / "r.png"
    assert main(["data", "render", "--root", str(out), "--info", str(info), "--frames", "0,4", "--out", str(png)]) == 0
    assert Image.open(png).size == (404, 200)


@pytest.fixture
def no_work(monkeypatch):
    """Make generating a scene, rendering and exporting fail loudly: the checks must come first."""
    import t3fast.data.export
    import t3fast.viz.bev
    from t3fast.data.synthetic.dataset import SyntheticScenes

    def refuse(*args, **kwargs):
        raise AssertionError("did work before checking the arguments")

    monkeypatch.setattr(SyntheticScenes, "generate", refuse)
    monkeypatch.setattr(t3fast.viz.bev, "save_sample_png", refuse)
    monkeypatch.setattr(t3fast.data.export, "export_synthetic", refuse)


RENDER = ["data", "render", "--scenes", "1", "--frames-per-scene", "11", "--out"]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--frames", "0,2,99"], "--frames 0,2,99: frame 99 is out of range; a window has frames 0..10"),
        (["--frames", "-1"], "frame -1 is out of range"),
        (["--frames", "0,x"], "--frames '0,x': expected comma-separated frame numbers"),
        (["--scale", "100000"], "--scale 100000: expected 1..6 for 6 frames (the picture may be at most 8192 pixels"),
        (["--scale", "0"], "--scale 0: expected 1..6"),
        (["--frames", "0,1", "--scale", "21"], "--scale 21: expected 1..20 for 2 frames"),
        (["--frames", ",".join(["0"] * 41)], "41 frames do not fit in a picture 8192 pixels wide"),
        (["--frames-per-scene", "5000"], "--frames-per-scene 5000: expected 11..1000 frames per scene"),
    ],
)
def test_render_refuses_bad_arguments_up_front(tmp_path, capsys, no_work, extra, message):
    assert main([*RENDER, str(tmp_path / "r.png"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("t3fast data render: ") and err.count("\n") == 1 and message in err
    assert not (tmp_path / "r.png").exists()


def test_largest_allowed_render_fits(tmp_path):
    from t3fast.commands.data import MAX_IMAGE_SIDE, _render_frames

    assert _render_frames("0,2,4,6,8,10", 6) == [0, 2, 4, 6, 8, 10]  # 7220 pixels wide
    assert _render_frames("4", MAX_IMAGE_SIDE // 200) == [4]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--frames", "100000000"], "--frames 100000000: expected 11..1000 frames per scene"),
        (["--frames", "5"], "--frames 5: expected 11..1000"),
        (["--scenes", "0"], "--scenes 0: expected 1..1000000"),
    ],
)
def test_export_refuses_bad_counts_up_front(tmp_path, capsys, no_work, extra, message):
    assert main(["data", "export-synthetic", "--out", str(tmp_path / "exp"), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("t3fast data export-synthetic: ") and message in err
    assert not (tmp_path / "exp").exists()


def test_stats_refuses_too_many_frames_up_front(capsys, no_work):
    assert main(["data", "stats", "--scenes", "1", "--frames-per-scene", "1001"]) == 2
    assert "--frames-per-scene 1001: expected 11..1000" in capsys.readouterr().err


def test_synthetic_scenes_bound_their_length():
    from t3fast.data.synthetic.dataset import MAX_FRAMES_PER_SCENE, SyntheticScenes

    assert SyntheticScenes("val", 1, MAX_FRAMES_PER_SCENE).frames_per_scene == MAX_FRAMES_PER_SCENE
    with pytest.raises(ValueError, match="frames_per_scene must be 11..1000"):
        SyntheticScenes("val", 1, 100_000_000)
