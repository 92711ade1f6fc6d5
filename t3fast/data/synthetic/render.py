"""Cut ego-frame Occ3D label volumes out of the static raster and draw agent boxes.

Frames are indexed ``[x, y, z]`` in the ego frame (x forward, y left, z up);
see ``t3fast.data.classes`` for the grid geometry.
"""

from __future__ import annotations

import numpy as np

from t3fast.data import classes as C
from t3fast.data.synthetic.layout import Warp
from t3fast.data.synthetic.world import GROUND_TOP, GROUND_Z, MAX_RAISE, ON_GROUND, RES, StaticMap, z_level

_XC = C.voxel_centers(0)
_YC = C.voxel_centers(1)
_LEVELS = np.arange(C.GRID_SHAPE[2], dtype=np.uint8)


def render_static(static: StaticMap, warp: Warp, pose: np.ndarray) -> np.ndarray:
    """Static world seen from ego ``pose`` (x, y, yaw in world coordinates): uint8 ``[200, 200, 16]``.

    Nearest-neighbour lookup of each voxel column centre in the 0.2 m raster. The ground fills
    levels ``GROUND_Z .. GROUND_Z + ground_h`` wherever no object column occupies them.
    """
    px, py, yaw = pose
    c, s = np.cos(yaw), np.sin(yaw)
    wx = px + c * _XC[:, None] - s * _YC[None, :]
    wy = py + s * _XC[:, None] + c * _YC[None, :]
    u, v = warp.to_town(wx, wy)
    i = np.floor((u - static.u0) / RES).astype(np.int64)
    j = np.floor((v - static.v0) / RES).astype(np.int64)
    h, w = static.ground.shape
    if i.min() < 0 or j.min() < 0 or i.max() >= h or j.max() >= w:
        raise ValueError("ego view leaves the rasterised town; enlarge the raster margin")
    obj = static.obj[i, j]
    occupied = (_LEVELS >= static.z0[i, j][..., None]) & (_LEVELS < static.z1[i, j][..., None])
    vol = np.where(occupied, obj[..., None], np.uint8(C.FREE))
    levels = slice(GROUND_Z, GROUND_Z + MAX_RAISE + 1)
    in_ground = _LEVELS[levels] <= GROUND_Z + static.ground_h[i, j][..., None]
    vol[..., levels] = np.where(in_ground & ~occupied[..., levels], static.ground[i, j][..., None], vol[..., levels])
    return vol


def draw_boxes(vol: np.ndarray, boxes: np.ndarray, labels: np.ndarray) -> None:
    """Draw ego-frame boxes ``[N, 7]`` (x, y, z, l, w, h, yaw) with class ids ``[N]`` into ``vol`` in place.

    A voxel column is filled when its centre lies inside the footprint; the column
    under the box centre is always filled so small agents never vanish.
    """
    for (x, y, _z, length, width, height, yaw), label in zip(boxes, labels):
        footprint = C.box_footprint(x, y, length, width, yaw, vol.shape[:2])
        if footprint is not None:
            rows, cols, inside = footprint
            vol[rows, cols, ON_GROUND : z_level(height)][inside] = label


def box_z(height: np.ndarray) -> np.ndarray:
    """Centre height (m) of a box of ``height`` standing on the ground."""
    return GROUND_TOP + height / 2
