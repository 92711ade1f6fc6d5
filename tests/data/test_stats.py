"""``t3fast data stats``: height profiles and free share of synthetic splits and Occ3D folders."""

import argparse

import numpy as np
import pytest

from t3fast.commands.data import add_data_commands
from t3fast.data import classes as C
from t3fast.data.stats import format_height_profile, height_profile
from tests.data.conftest import FRAMES, SCENES, SPLIT


def _parse(argv: list[str]) -> argparse.Namespace:
    root = argparse.ArgumentParser()
    add_data_commands(root.add_subparsers(dest="command"))
    return root.parse_args(argv)


def test_height_profile_counts_class_per_z():
    vol = np.full((200, 200, 16), C.FREE, dtype=np.uint8)
    vol[:, :, 0] = C.DRIVEABLE_SURFACE
    vol[:10, :10, 7] = C.VEGETATION
    vol[0, 0, 15] = 255  # ignore is left out
    profile, frames = height_profile([vol, vol])
    assert frames == 2 and profile.shape == (C.NUM_CLASSES, 16)
    assert profile[C.DRIVEABLE_SURFACE].tolist() == [80000] + [0] * 15
    assert profile[C.VEGETATION, 7] == 200 and profile[C.VEGETATION].sum() == 200
    text = format_height_profile(profile, frames)
    assert "driveable_surface" in text and "bus" not in text
    assert f"free: {100 * profile[C.FREE].sum() / profile.sum():.1f} %" in text


def test_stats_on_synthetic(capsys):
    args = _parse(["data", "stats", "--split", SPLIT, "--scenes", str(SCENES), "--frames-per-scene", str(FRAMES)])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "voxels per frame at each z index" in out and "free:" in out
    ground = next(line for line in out.splitlines() if line.startswith("driveable_surface") and "  0 " in line[22:])
    values = ground.split()[1:17]
    assert float(values[0]) > 1000 and all(float(v) == 0 for v in values[1:])  # the road is level 0 only


def test_stats_on_exported_occ3d_folder(exported, capsys):
    root, _ = exported
    args = _parse(["data", "stats", "--occ3d", str(root)])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert f"{SCENES * FRAMES} frames" in out and "free:" in out and "manmade" in out


@pytest.mark.parametrize("scenes", ["0", "-2"])
def test_stats_rejects_non_positive_scene_counts(scenes):
    args = _parse(["data", "stats", "--scenes", scenes])
    with pytest.raises(ValueError, match="--scenes"):
        args.func(args)


def test_stats_rejects_an_empty_occ3d_folder(tmp_path):
    args = _parse(["data", "stats", "--occ3d", str(tmp_path)])
    with pytest.raises(ValueError, match="labels.npz"):
        args.func(args)
