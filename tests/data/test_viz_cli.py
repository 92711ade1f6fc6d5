import numpy as np
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
