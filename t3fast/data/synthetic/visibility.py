"""Camera visibility mask by ray casting from the ego, like Occ3D's ``mask_camera``.

Occlusion is cast over the height field of the scene: every voxel column counts
as solid from the ground up to its highest occupied voxel (an overhanging tree
crown therefore also hides what is under it). Rays leave the sensor along a
fixed set of azimuths; along each ray the running maximum of the elevation
angle of the column tops seen so far is the horizon. A voxel is visible when the
top of the voxel rises above the horizon of the columns nearer than it, so the
first surface hit along any ray is visible and everything behind it is not.
The polar sample positions are fixed, so their column indices are computed once;
each frame costs a column-top reduction, one gather and one cumulative maximum.
"""

from __future__ import annotations

import numpy as np

from t3fast.data import classes as C

SENSOR_Z = 1.0  # m, camera height in the ego frame (1.6 m above the ground top at -0.6 m)
AZIMUTH_STEP = np.deg2rad(0.4)
RAY_STEP = 0.2  # m between samples along a ray
SELF_GAP = 0.4  # m: columns nearer than this to a voxel do not occlude it (its own column)


class RayCaster:
    """Precomputed rays over the Occ3D grid; ``visible(occ)`` -> bool ``[200, 200, 16]``."""

    def __init__(self) -> None:
        nx, ny, nz = C.GRID_SHAPE
        vs = C.VOXEL_SIZE
        lo = C.GRID_LOWER
        n_az = int(round(2 * np.pi / AZIMUTH_STEP))
        az = np.arange(n_az) * AZIMUTH_STEP
        r = np.arange(1, int(np.hypot(C.GRID_UPPER[0], C.GRID_UPPER[1]) / RAY_STEP) + 2) * RAY_STEP
        x = r[None, :] * np.cos(az)[:, None]
        y = r[None, :] * np.sin(az)[:, None]
        i = np.floor((x - lo[0]) / vs).astype(np.int64)
        j = np.floor((y - lo[1]) / vs).astype(np.int64)
        inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        # samples outside the grid look at a free sentinel column
        self.ray_column = np.where(inside, i * ny + j, nx * ny)  # [n_az, n_r]
        self.ray_range = r
        self.lag = int(np.ceil(SELF_GAP / RAY_STEP))
        xc, yc = C.voxel_centers(0), C.voxel_centers(1)
        horiz = np.hypot(xc[:, None], yc[None, :])
        a_idx = np.round(np.mod(np.arctan2(yc[None, :], xc[:, None]), 2 * np.pi) / AZIMUTH_STEP).astype(np.int64)
        r_idx = np.clip(np.round(horiz / RAY_STEP).astype(np.int64) - 1, 0, len(r) - 1)
        self.column_bin = (a_idx % n_az) * len(r) + r_idx  # [200, 200] -> flat (azimuth, range) bin
        level_top = lo[2] + vs * (np.arange(nz) + 1)
        # elevation angle of each voxel's top as seen from the sensor, [200, 200, 16]
        self.voxel_elevation = np.arctan2(level_top[None, None, :] - SENSOR_Z, horiz[..., None])
        self.level_top = level_top
        # steep rays reach a voxel through the voxel above (looking down) or below (looking up);
        # 30 degrees rather than 45 because rays are cast to voxel centres from a coarse bin
        level_mid = lo[2] + vs * (np.arange(nz) + 0.5)
        centre_elevation = np.arctan2(level_mid[None, None, :] - SENSOR_Z, horiz[..., None])
        self.steep_down = centre_elevation < -np.pi / 6
        self.steep_up = centre_elevation > np.pi / 6

    def visible(self, occ: np.ndarray) -> np.ndarray:
        """Visibility of every voxel of one label volume ``[200, 200, 16]`` -> bool, same shape."""
        occupied = occ != C.FREE
        nz = occ.shape[2]
        any_occ = occupied.any(axis=2)
        top_level = nz - 1 - np.argmax(occupied[..., ::-1], axis=2)
        top_z = np.where(any_occ, self.level_top[top_level], -np.inf).reshape(-1)
        top_z = np.append(top_z, -np.inf)
        elev = np.arctan2(top_z[self.ray_column] - SENSOR_Z, self.ray_range[None, :])
        horizon = np.maximum.accumulate(elev, axis=1)
        # a voxel is occluded only by columns at least SELF_GAP nearer
        shifted = np.full_like(horizon, -np.inf)
        shifted[:, self.lag :] = horizon[:, : -self.lag]
        h = shifted.reshape(-1)[self.column_bin]
        visible = self.voxel_elevation >= h[..., None]
        # the height field ignores a voxel's own column; steep rays are blocked by its neighbour in z
        visible[:, :, :-1] &= ~(self.steep_down[:, :, :-1] & occupied[:, :, 1:])
        visible[:, :, 1:] &= ~(self.steep_up[:, :, 1:] & occupied[:, :, :-1])
        return visible


_CASTER: RayCaster | None = None


def camera_mask(occ: np.ndarray) -> np.ndarray:
    """``mask_camera`` of one ego-frame label volume ``[200, 200, 16]`` (bool, True = observed)."""
    global _CASTER
    if _CASTER is None:
        _CASTER = RayCaster()
    return _CASTER.visible(occ)
