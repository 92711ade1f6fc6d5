"""Driving data for T3Former: synthetic towns and Occ3D-nuScenes, one sample structure.

* ``classes``: Occ3D class ids, palette, grid geometry (labels ``uint8 [200, 200, 16]``
  indexed ``[x, y, z]``, ego frame x forward / y left / z up, 0.4 m voxels,
  x, y in [-40, 40] m, z in [-1, 5.4] m).
* ``SyntheticDriving`` / ``SyntheticFrames``: procedural scenes, no download.
* ``Occ3DNuScenes``: ``gts/<scene>/<token>/labels.npz`` + an OccWorld-style info pickle.
* ``DrivingSample`` / ``collate_samples``: 11 frames (4 past, present = index 4,
  6 future), actions in the present frame, boxes in the present frame
  (see ``t3fast.data.sample``).
"""

from t3fast.data.occ3d import Occ3DFormatError, Occ3DNuScenes, read_labels
from t3fast.data.sample import (
    NUM_FUTURE,
    NUM_PAST,
    PRESENT,
    WINDOW,
    DrivingBatch,
    DrivingSample,
    collate_samples,
    flip_sample,
    random_flip,
)
from t3fast.data.synthetic import SyntheticDriving, SyntheticFrames, generate_scene

__all__ = [
    "NUM_FUTURE",
    "NUM_PAST",
    "PRESENT",
    "WINDOW",
    "DrivingBatch",
    "DrivingSample",
    "Occ3DFormatError",
    "Occ3DNuScenes",
    "SyntheticDriving",
    "SyntheticFrames",
    "collate_samples",
    "flip_sample",
    "generate_scene",
    "random_flip",
    "read_labels",
]
