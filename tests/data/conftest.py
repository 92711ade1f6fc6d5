"""Shared small synthetic data for the data tests (few, short scenes to stay fast)."""

from __future__ import annotations

import pytest

from t3fast.data.export import export_synthetic
from t3fast.data.synthetic.dataset import SyntheticDriving

SPLIT = "val"
SCENES = 2
FRAMES = 14


@pytest.fixture(scope="session")
def synthetic() -> SyntheticDriving:
    return SyntheticDriving(SPLIT, num_scenes=SCENES, frames_per_scene=FRAMES)


@pytest.fixture(scope="session")
def exported(tmp_path_factory):
    """(root, info path) of the same scenes written in the Occ3D layout."""
    root = tmp_path_factory.mktemp("occ3d")
    info = export_synthetic(root, SPLIT, SCENES, FRAMES, progress=False)
    return root, info
