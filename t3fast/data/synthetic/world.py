"""The static town rasterised once, at 0.2 m, in town coordinates.

The vertical layout follows Occ3D-nuScenes: the ground (road, sidewalk, terrain,
other_flat) is voxel level ``GROUND_Z`` = 0 (-1.0 to -0.6 m), raised by
``ground_h`` extra levels (at most two) for kerbed sidewalks, medians and grass
mounds, always filled down to level 0. Each cell also holds at most one object
column: a class with a ``[z0, z1)`` range of voxel levels. Buildings, walls,
hedges and tree trunks start at level 0 (their base replaces the ground); poles
and street furniture stand on the ground, from level 1. A tree is a trunk column
merged with a crown column of the same class. Frames are then cut out of this
raster by ``render.render_static`` with pure index arithmetic.

Occ3D labels only what LiDAR saw over a drive, so buildings are street facades
(with short side returns, a roof edge when under the grid top, and set-back upper
floors) and the ground behind them is left free, as are lots with no street front.

Contents: sidewalks along every road (kerbs rounded at the corners) (crosswalks are the sidewalk lines
continuing over the carriageway, labelled driveable_surface as in Occ3D),
raised medians (other_flat) and median barriers, street lights, signs, curb
trees, street furniture ("others") and kerbside traffic cones, and one of four block types per block:
buildings on random lots (manmade, varied footprint and height) with front
walls, hedges, courtyards and lawns, a park (terrain with mounds, trees, bushes,
paths, benches), a parking lot (other_flat, parked cars, light poles) or a
construction site (barrier fence, traffic cones, material piles, construction vehicles).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from t3fast.data import classes as C
from t3fast.data.synthetic.layout import RoadNetwork

RES = 0.2  # metres per raster cell
KERB_RADIUS = 4.25  # m: right turns use a 6 m arc 1.75 m from the kerb
GROUND_Z = 0  # voxel level of the ground surface (z in [-1.0, -0.6) m), as in Occ3D-nuScenes
GROUND_TOP = C.GRID_LOWER[2] + (GROUND_Z + 1) * C.VOXEL_SIZE  # -0.6 m
GROUND_CLASSES = (C.DRIVEABLE_SURFACE, C.OTHER_FLAT, C.SIDEWALK, C.TERRAIN)
MAX_RAISE = 2  # ground levels above GROUND_Z a cell may be raised by (kerbs: 1, mounds: 2)
NZ = C.GRID_SHAPE[2]
ON_GROUND = GROUND_Z + 1  # lowest level of things standing on the ground
FACADE = 0.6  # m, wall thickness: at least one voxel column whatever the ego's heading
UNSEEN_DEPTH = 5.0  # m behind the kerb beyond which the street's LiDAR misses the ground


def z_level(height: float) -> int:
    """Exclusive top voxel level of something standing on the ground ``height`` metres tall."""
    return int(min(NZ, ON_GROUND + max(1, round(height / C.VOXEL_SIZE))))


@dataclass
class StaticAgents:
    """Parked vehicles: town-coordinate centre ``[M, 2]``, axis-aligned heading ``[M, 2]``,
    size ``[M, 3]`` (l, w, h) and class id ``[M]``."""

    centre: list = field(default_factory=list)
    heading: list = field(default_factory=list)
    size: list = field(default_factory=list)
    label: list = field(default_factory=list)

    def add(self, u: float, v: float, along_u: bool, size: tuple[float, float, float], label: int) -> None:
        self.centre.append((u, v))
        self.heading.append((1.0, 0.0) if along_u else (0.0, 1.0))
        self.size.append(size)
        self.label.append(label)


class StaticMap:
    """The raster: ``ground`` (class or FREE), ``ground_h`` (extra ground levels, 0..MAX_RAISE),
    ``obj`` (class or FREE), ``z0``, ``z1``, all ``[H, W]`` uint8, cell ``(i, j)`` covering
    ``u in u0 + RES*[i, i+1)``, ``v in v0 + RES*[j, j+1)``."""

    def __init__(self, u0: float, v0: float, shape: tuple[int, int]):
        self.u0, self.v0 = u0, v0
        self.ground = np.full(shape, C.TERRAIN, dtype=np.uint8)
        self.ground_h = np.zeros(shape, dtype=np.uint8)
        self.obj = np.full(shape, C.FREE, dtype=np.uint8)
        self.z0 = np.zeros(shape, dtype=np.uint8)
        self.z1 = np.zeros(shape, dtype=np.uint8)

    def _slices(self, u_lo: float, u_hi: float, v_lo: float, v_hi: float) -> tuple[slice, slice] | None:
        h, w = self.ground.shape
        i0 = max(int(np.floor((u_lo - self.u0) / RES)), 0)
        i1 = min(int(np.ceil((u_hi - self.u0) / RES)), h)
        j0 = max(int(np.floor((v_lo - self.v0) / RES)), 0)
        j1 = min(int(np.ceil((v_hi - self.v0) / RES)), w)
        if i0 >= i1 or j0 >= j1:
            return None
        return slice(i0, i1), slice(j0, j1)

    def ground_rect(self, label: int, u_lo: float, u_hi: float, v_lo: float, v_hi: float, raised: int = 0) -> None:
        """Ground of class ``label`` (FREE: never observed) over a rectangle, ``raised`` levels up."""
        sl = self._slices(u_lo, u_hi, v_lo, v_hi)
        if sl is not None:
            self.ground[sl] = label
            self.ground_h[sl] = raised if label != C.FREE else 0

    def mound(self, cu: float, cv: float, radius: float) -> None:
        """A grass bank: ground raised one level within ``radius`` m, two within half of it."""
        sl = self._slices(cu - radius, cu + radius, cv - radius, cv + radius)
        if sl is None:
            return
        uu = self.u0 + RES * (np.arange(sl[0].start, sl[0].stop) + 0.5) - cu
        vv = self.v0 + RES * (np.arange(sl[1].start, sl[1].stop) + 0.5) - cv
        r = np.hypot(uu[:, None], vv[None, :]) / radius
        rise = np.where(self.ground[sl] == C.TERRAIN, (r < 1.0).astype(np.uint8) + (r < 0.5), 0)
        self.ground_h[sl] = np.maximum(self.ground_h[sl], rise.astype(np.uint8))

    def box(self, label: int, u_lo: float, u_hi: float, v_lo: float, v_hi: float, z0: int, z1: int) -> None:
        """An axis-aligned block of class ``label`` over voxel levels ``[z0, z1)``."""
        sl = self._slices(u_lo, u_hi, v_lo, v_hi)
        if sl is not None:
            self._paint(sl, np.ones(self.obj[sl].shape, bool), label, np.uint8(z0), np.uint8(z1))

    def building(self, rect: tuple[float, float, float, float], faces: tuple[bool, bool, bool, bool],
                 z0: int, z1: int, depth: float = 4.0) -> None:
        """A building as Occ3D sees it from the street, over levels ``[z0, z1)``.

        ``rect`` is (u_lo, u_hi, v_lo, v_hi); ``faces`` says which of those four sides face a
        street. Each street side gets a facade with returns ``depth`` m deep on its neighbours:
        LiDAR from the street reaches neither the back, the inside nor the roof, which Occ3D
        leaves free.
        """
        u_lo, u_hi, v_lo, v_hi = rect
        for side, facing in enumerate(faces):
            if not facing:
                continue
            if side < 2:
                a, b = (u_lo, u_lo + FACADE) if side == 0 else (u_hi - FACADE, u_hi)
                self.box(C.MANMADE, a, b, v_lo, v_hi, z0, z1)
                a, b = (u_lo, u_lo + depth) if side == 0 else (u_hi - depth, u_hi)
                self.box(C.MANMADE, a, b, v_lo, v_lo + FACADE, z0, z1)
                self.box(C.MANMADE, a, b, v_hi - FACADE, v_hi, z0, z1)
            else:
                a, b = (v_lo, v_lo + FACADE) if side == 2 else (v_hi - FACADE, v_hi)
                self.box(C.MANMADE, u_lo, u_hi, a, b, z0, z1)
                a, b = (v_lo, v_lo + depth) if side == 2 else (v_hi - depth, v_hi)
                self.box(C.MANMADE, u_lo, u_lo + FACADE, a, b, z0, z1)
                self.box(C.MANMADE, u_hi - FACADE, u_hi, a, b, z0, z1)

    def blob(self, label: int, cu: float, cv: float, radius: float, z_mid: float, half_height: float,
             z_floor: int = ON_GROUND) -> None:
        """An ellipsoid (tree crown, bush): disc of ``radius`` m, levels ``z_mid +- half_height`` at its
        axis, cut at level ``z_floor``."""
        sl = self._slices(cu - radius, cu + radius, cv - radius, cv + radius)
        if sl is None:
            return
        uu = self.u0 + RES * (np.arange(sl[0].start, sl[0].stop) + 0.5) - cu
        vv = self.v0 + RES * (np.arange(sl[1].start, sl[1].stop) + 0.5) - cv
        r2 = (uu[:, None] ** 2 + vv[None, :] ** 2) / radius**2
        inside = r2 < 1.0
        hz = half_height * np.sqrt(np.clip(1.0 - r2, 0.0, None))
        z0 = np.clip(np.round(z_mid - hz), z_floor, NZ).astype(np.uint8)
        z1 = np.clip(np.round(z_mid + hz) + 1, z_floor + 1, NZ).astype(np.uint8)
        self._paint(sl, inside, label, z0, z1)

    def _paint(self, sl: tuple[slice, slice], where: np.ndarray, label: int, z0, z1) -> None:
        obj, lo, hi = self.obj[sl], self.z0[sl], self.z1[sl]
        z0 = np.broadcast_to(z0, where.shape)
        z1 = np.broadcast_to(z1, where.shape)
        same = where & (obj == label)  # same class: merge into one column (trunk + crown)
        other = where & ~same
        lo[same] = np.minimum(lo[same], z0[same])
        hi[same] = np.maximum(hi[same], z1[same])
        obj[other], lo[other], hi[other] = label, z0[other], z1[other]


def _round_corners(m: StaticMap, net: RoadNetwork, lo: np.ndarray, hi: np.ndarray) -> None:
    """Round the kerb at every intersection corner with radius ``KERB_RADIUS``, so that right
    turns (which keep 1.75 m from the kerb on a concentric arc) stay on the carriageway."""
    r = KERB_RADIUS
    for ru in net.roads[0]:
        for rv in net.roads[1]:
            if not (lo[0] - 20 < rv.pos < hi[0] + 20 and lo[1] - 20 < ru.pos < hi[1] + 20):
                continue
            for su in (-1.0, 1.0):
                for sv in (-1.0, 1.0):
                    cu, cv = rv.pos + su * rv.half_width, ru.pos + sv * ru.half_width  # kerb corner
                    sl = m._slices(min(cu, cu + su * r), max(cu, cu + su * r), min(cv, cv + sv * r),
                                   max(cv, cv + sv * r))
                    if sl is None:
                        continue
                    uu = m.u0 + RES * (np.arange(sl[0].start, sl[0].stop) + 0.5)
                    vv = m.v0 + RES * (np.arange(sl[1].start, sl[1].stop) + 0.5)
                    du = uu[:, None] - (cu + su * r)
                    dv = vv[None, :] - (cv + sv * r)
                    outside = du**2 + dv**2 > r**2
                    m.ground[sl][outside] = C.DRIVEABLE_SURFACE
                    m.ground_h[sl][outside] = 0
                    m.obj[sl][outside] = C.FREE


def _split_lots(rng: np.random.Generator, rect: tuple[float, float, float, float], out: list) -> None:
    """Binary space partition of a block into building lots of 10-35 m."""
    u0, u1, v0, v1 = rect
    du, dv = u1 - u0, v1 - v0
    if max(du, dv) < 35.0 and rng.random() < 0.7 or max(du, dv) < 20.0:
        out.append(rect)
        return
    if du >= dv:
        cut = rng.uniform(u0 + 0.35 * du, u1 - 0.35 * du)
        _split_lots(rng, (u0, cut, v0, v1), out)
        _split_lots(rng, (cut, u1, v0, v1), out)
    else:
        cut = rng.uniform(v0 + 0.35 * dv, v1 - 0.35 * dv)
        _split_lots(rng, (u0, u1, v0, cut), out)
        _split_lots(rng, (u0, u1, cut, v1), out)


def _tree(m: StaticMap, rng: np.random.Generator, u: float, v: float, big: bool,
          away: tuple[float, float] = (0.0, 0.0)) -> None:
    """Trunk from the ground into an ellipsoid crown.

    Crowns are widest 2.4-4 m above the ground (levels 7-10 with the ground at 0), as in
    Occ3D-nuScenes; big trees reach past the grid top. ``away`` (a unit vector or zero)
    shifts the crown so that it ends 0.6 m beyond the trunk on the other side: street
    trees are trimmed clear of the carriageway, where trucks and buses pass under.
    """
    if big:
        radius, bottom, top = rng.uniform(2.0, 3.4), rng.uniform(1.2, 2.2), rng.uniform(4.6, 8.5)
    else:
        radius, bottom, top = rng.uniform(1.3, 2.1), rng.uniform(2.0, 2.6), rng.uniform(4.2, 5.8)
    m.box(C.VEGETATION, u - 0.25, u + 0.25, v - 0.25, v + 0.25, GROUND_Z, z_level(bottom + 0.8))
    zb = ON_GROUND + bottom / C.VOXEL_SIZE
    zt = ON_GROUND + top / C.VOXEL_SIZE
    shift = radius - 0.6
    m.blob(C.VEGETATION, u + shift * away[0], v + shift * away[1], radius, (zb + zt) / 2, (zt - zb) / 2)


def _bush(m: StaticMap, rng: np.random.Generator, u: float, v: float) -> None:
    """A bush growing out of the ground (from level 0) up to about 2 m."""
    m.blob(C.VEGETATION, u, v, rng.uniform(0.8, 2.0), ON_GROUND + 0.5, rng.uniform(1.5, 4.0), z_floor=GROUND_Z)


def _facing(lot: tuple[float, float, float, float], inner: tuple[float, float, float, float]) -> tuple[bool, ...]:
    """Which sides (u_lo, u_hi, v_lo, v_hi) of a lot lie on its block's street front."""
    return tuple(abs(a - b) < 1e-6 for a, b in zip(lot, inner))


def _lot_building(m: StaticMap, rng: np.random.Generator, lot, faces: tuple[bool, ...]) -> None:
    """A building on a street-facing lot: front margin, facade height, maybe set-back upper floors,
    maybe a front wall or hedge; the ground behind the facades is never observed (free)."""
    lu0, lu1, lv0, lv1 = lot
    margin = np.where(faces, rng.uniform(0.0, 3.0, size=4), rng.uniform(0.0, 1.5, size=4))
    rect = (lu0 + margin[0], lu1 - margin[1], lv0 + margin[2], lv1 - margin[3])
    if rect[1] - rect[0] < 6.0 or rect[3] - rect[2] < 6.0:
        return
    # the free part: the lot minus its front margins
    m.ground_rect(C.FREE, *(edge if f else outer for edge, f, outer in zip(rect, faces, lot)))
    low = rng.random() < 0.25
    height = rng.uniform(2.6, 5.0) if low else rng.uniform(6.0, 40.0)
    if not low and rng.random() < 0.45:  # podium with set-back upper floors
        podium = z_level(rng.uniform(3.0, 4.6))
        m.building(rect, faces, GROUND_Z, podium)
        inset = rng.uniform(2.0, 5.0)
        upper = tuple(r + (inset if k % 2 == 0 else -inset) * f for k, (r, f) in enumerate(zip(rect, faces)))
        m.building(upper, faces, podium - 1, z_level(height))
    else:
        m.building(rect, faces, GROUND_Z, z_level(height))
    for side, facing in enumerate(faces):  # front wall or hedge along the lot edge
        if not facing or margin[side] < 1.2 or rng.random() < 0.5:
            continue
        edge = lot[side] + (0.25 if side % 2 == 0 else -0.25)
        a0, a1 = (lv0, lv1) if side < 2 else (lu0, lu1)
        sides = (edge - 0.25, edge + 0.25, a0, a1) if side < 2 else (a0, a1, edge - 0.25, edge + 0.25)
        if rng.random() < 0.5:
            m.box(C.MANMADE, *sides, GROUND_Z, z_level(rng.uniform(0.8, 1.8)))
        else:
            m.box(C.VEGETATION, *sides, GROUND_Z, z_level(rng.uniform(0.8, 1.6)))


def _urban_block(m: StaticMap, rng: np.random.Generator, rect) -> None:
    u0, u1, v0, v1 = rect
    setback = rng.uniform(0.0, 4.0)
    m.ground_rect(C.TERRAIN if rng.random() < 0.6 else C.OTHER_FLAT, u0, u1, v0, v1)
    inner = (u0 + setback, u1 - setback, v0 + setback, v1 - setback)
    if setback > 2.0:  # lawn strip with trees, bushes and the odd bench
        for edge_u in (u0 + setback / 2, u1 - setback / 2):
            for v in np.arange(v0 + 5, v1 - 5, rng.uniform(7, 14)):
                kind = rng.random()
                if kind < 0.5:
                    _tree(m, rng, edge_u, v, big=False)
                elif kind < 0.75:
                    _bush(m, rng, edge_u, v)
                elif kind < 0.85:
                    m.box(C.OTHERS, edge_u - 0.4, edge_u + 0.4, v - 0.8, v + 0.8, ON_GROUND, z_level(0.8))
    lots: list = []
    _split_lots(rng, inner, lots)
    for lot in lots:
        faces = _facing(lot, inner)
        lu0, lu1, lv0, lv1 = lot
        if not any(faces):  # no street front: never observed
            m.ground_rect(C.FREE, *lot)
        elif rng.random() < 0.82:
            _lot_building(m, rng, lot, faces)
        else:  # courtyard: paved or green, a tree or two, a bin
            m.ground_rect(C.OTHER_FLAT if rng.random() < 0.5 else C.TERRAIN, lu0, lu1, lv0, lv1)
            for _ in range(rng.integers(0, 3)):
                _tree(m, rng, rng.uniform(lu0 + 2, lu1 - 2), rng.uniform(lv0 + 2, lv1 - 2), big=True)
            cu, cv = rng.uniform(lu0 + 1, lu1 - 1), rng.uniform(lv0 + 1, lv1 - 1)
            m.box(C.OTHERS, cu - 0.5, cu + 0.5, cv - 0.5, cv + 0.5, ON_GROUND, z_level(1.2))


def _park(m: StaticMap, rng: np.random.Generator, rect) -> None:
    u0, u1, v0, v1 = rect
    m.ground_rect(C.TERRAIN, u0, u1, v0, v1)
    pu = rng.uniform(u0 + 5, u1 - 5)
    m.ground_rect(C.OTHER_FLAT, pu - 1.2, pu + 1.2, v0, v1)  # footpath
    area = (u1 - u0) * (v1 - v0)
    for v in (v0 + 4.0, v1 - 4.0):  # grass banks along the street fronts, clear of the path
        u = rng.uniform(u0 + 6, u1 - 6)
        if abs(u - pu) > 8.0 and rng.random() < 0.6:
            m.mound(u, v, rng.uniform(3.0, 5.0))
    for _ in range(int(area / rng.uniform(90, 200))):
        u, v = rng.uniform(u0 + 3.0, u1 - 3.0), rng.uniform(v0 + 3.0, v1 - 3.0)  # crowns clear of the road
        if abs(u - pu) < 4.0:
            continue
        if rng.random() < 0.65:
            _tree(m, rng, u, v, big=True)
        else:
            _bush(m, rng, u, v)
    for v in np.arange(v0 + 6, v1 - 6, rng.uniform(12, 25)):  # benches along the path
        m.box(C.OTHERS, pu + 1.4, pu + 2.0, v - 0.9, v + 0.9, ON_GROUND, z_level(0.8))


def _parking(m: StaticMap, rng: np.random.Generator, rect, parked: StaticAgents) -> None:
    u0, u1, v0, v1 = rect
    m.ground_rect(C.OTHER_FLAT, u0, u1, v0, v1)
    for row_v in np.arange(v0 + 3.5, v1 - 3.0, 13.0):  # rows of bays facing each other across an aisle
        for v_centre in (row_v, row_v + 6.0):
            if v_centre + 2.5 > v1:
                continue
            for u in np.arange(u0 + 2.0, u1 - 2.0, 2.8):
                if rng.random() < 0.45:
                    size = (rng.uniform(4.0, 5.0), rng.uniform(1.75, 2.0), rng.uniform(1.4, 1.9))
                    parked.add(u, v_centre, along_u=False, size=size, label=C.CAR)
    for u in np.arange(u0 + 1.0, u1, 20.0):  # light poles on the edges
        for v in (v0 + 0.5, v1 - 0.5):
            m.box(C.MANMADE, u - 0.2, u + 0.2, v - 0.2, v + 0.2, ON_GROUND, z_level(7.0))


def _construction(m: StaticMap, rng: np.random.Generator, rect, parked: StaticAgents) -> None:
    u0, u1, v0, v1 = rect
    m.ground_rect(C.TERRAIN, u0, u1, v0, v1)
    m.ground_rect(C.OTHER_FLAT, u0 + 4, u1 - 4, v0 + 4, v1 - 4)
    z_barrier = z_level(1.1)
    gap = rng.uniform(u0 + 6, u1 - 14)
    for vv in (v0 + 1.0, v1 - 1.0):  # fence with a gate
        m.box(C.BARRIER, u0 + 1.0, gap, vv - 0.25, vv + 0.25, GROUND_Z, z_barrier)
        m.box(C.BARRIER, gap + 8.0, u1 - 1.0, vv - 0.25, vv + 0.25, GROUND_Z, z_barrier)
    for uu in (u0 + 1.0, u1 - 1.0):
        m.box(C.BARRIER, uu - 0.25, uu + 0.25, v0 + 1.0, v1 - 1.0, GROUND_Z, z_barrier)
    for u in np.arange(gap + 0.5, gap + 8.0, 1.5):  # cones across the gate
        m.box(C.TRAFFIC_CONE, u - 0.2, u + 0.2, v0 + 2.2 - 0.2, v0 + 2.2 + 0.2, ON_GROUND, z_level(0.7))
    for _ in range(int(rng.integers(3, 9))):  # scattered cones and material piles
        u, v = rng.uniform(u0 + 5, u1 - 5), rng.uniform(v0 + 5, v1 - 5)
        if rng.random() < 0.5:
            m.box(C.TRAFFIC_CONE, u - 0.2, u + 0.2, v - 0.2, v + 0.2, ON_GROUND, z_level(0.7))
        else:
            m.box(C.OTHERS, u - 1.5, u + 1.5, v - 1.0, v + 1.0, ON_GROUND, z_level(rng.uniform(0.8, 2.0)))
    for k in range(int(rng.integers(1, 3))):
        cu = u0 + (k + 1) * (u1 - u0) / 3
        cv = (v0 + v1) / 2
        parked.add(cu, cv, along_u=bool(rng.random() < 0.5), size=(6.5, 2.8, 3.3), label=C.CONSTRUCTION_VEHICLE)


def _street_furniture(m: StaticMap, rng: np.random.Generator, net: RoadNetwork, lo: np.ndarray, hi: np.ndarray) -> None:
    """Street lights, signs, curb trees and hydrants/bins at the kerb side of every sidewalk."""
    for axis in (0, 1):
        crossing = net.roads[1 - axis]
        for road in net.roads[axis]:
            if not lo[1 - axis] - 20 < road.pos < hi[1 - axis] + 20:
                continue
            for side in (-1.0, 1.0):
                across = road.pos + side * (road.half_width + 0.5)
                along = lo[axis] + rng.uniform(0, 10)
                while along < hi[axis]:
                    along += rng.uniform(6.0, 12.0)
                    clear = all(abs(along - c.pos) > c.half_width + c.sidewalk + 1.0 for c in crossing)
                    if not clear:
                        continue
                    u, v = (along, across) if axis == 0 else (across, along)
                    kind = rng.random()
                    if kind < 0.25:  # street light
                        top = z_level(rng.uniform(5.5, 8.0))
                        m.box(C.MANMADE, u - 0.2, u + 0.2, v - 0.2, v + 0.2, ON_GROUND, top)
                    elif kind < 0.62:  # curb tree
                        _tree(m, rng, u, v, big=False, away=(0.0, side) if axis == 0 else (side, 0.0))
                    elif kind < 0.7:  # hydrant / bin
                        m.box(C.OTHERS, u - 0.25, u + 0.25, v - 0.25, v + 0.25, ON_GROUND, z_level(0.9))
                    elif kind < 0.76:  # a few cones around kerbside works
                        for k in range(3):
                            cu, cv = (u + 1.2 * k, v) if axis == 0 else (u, v + 1.2 * k)
                            m.box(C.TRAFFIC_CONE, cu - 0.2, cu + 0.2, cv - 0.2, cv + 0.2, ON_GROUND, z_level(0.7))
                    elif kind < 0.82:  # a run of jersey barriers along the kerb
                        run = rng.uniform(2.0, 6.0)
                        du, dv = (run, 0.3) if axis == 0 else (0.3, run)
                        m.box(C.BARRIER, u - du, u + du, v - dv, v + dv, GROUND_Z, z_level(0.9))
            # a sign on the right of each approach to each intersection
            for c in crossing:
                if not lo[axis] - 5 < c.pos < hi[axis] + 5:
                    continue
                for sigma in (-1.0, 1.0):
                    along = c.pos - sigma * (c.half_width + c.sidewalk + 2.0)
                    side = -sigma if axis == 0 else sigma
                    across = road.pos + side * (road.half_width + 0.5)
                    u, v = (along, across) if axis == 0 else (across, along)
                    m.box(C.MANMADE, u - 0.2, u + 0.2, v - 0.2, v + 0.2, ON_GROUND, z_level(2.8))
                    du, dv = (0.5, 0.2) if axis == 0 else (0.2, 0.5)
                    m.box(C.MANMADE, u - du, u + du, v - dv, v + dv, z_level(2.0), z_level(2.8))


def build_static_map(
    net: RoadNetwork, rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray
) -> tuple[StaticMap, StaticAgents]:
    """Rasterise the town over town-coordinate box ``[lo, hi]`` (each ``[2]``: u, v)."""
    shape = (int(np.ceil((hi[0] - lo[0]) / RES)), int(np.ceil((hi[1] - lo[1]) / RES)))
    m = StaticMap(float(lo[0]), float(lo[1]), shape)
    parked = StaticAgents()
    ru, rv = net.roads
    # blocks
    for i in range(len(ru) - 1):
        for j in range(len(rv) - 1):
            a, b, c, d = rv[j], rv[j + 1], ru[i], ru[i + 1]
            rect = (a.pos + a.half_width + a.sidewalk, b.pos - b.half_width - b.sidewalk,
                    c.pos + c.half_width + c.sidewalk, d.pos - d.half_width - d.sidewalk)
            if rect[1] < lo[0] or rect[0] > hi[0] or rect[3] < lo[1] or rect[2] > hi[1]:
                continue
            kind = rng.random()
            if kind < 0.58:
                _urban_block(m, rng, rect)
            elif kind < 0.78:
                _park(m, rng, rect)
            elif kind < 0.9:
                _parking(m, rng, rect, parked)
            else:
                _construction(m, rng, rect, parked)
    # sidewalks (most kerbed one level up), then carriageways over them (crosswalks are
    # carriageway), then medians
    for axis, roads in ((0, ru), (1, rv)):
        for r in roads:
            w = r.half_width + r.sidewalk
            raised = int(rng.random() < 0.5)
            if axis == 0:
                m.ground_rect(C.SIDEWALK, lo[0], hi[0], r.pos - w, r.pos + w, raised)
            else:
                m.ground_rect(C.SIDEWALK, r.pos - w, r.pos + w, lo[1], hi[1], raised)
    for axis, roads in ((0, ru), (1, rv)):
        for r in roads:
            w = r.half_width
            if axis == 0:
                m.ground_rect(C.DRIVEABLE_SURFACE, lo[0], hi[0], r.pos - w, r.pos + w)
            else:
                m.ground_rect(C.DRIVEABLE_SURFACE, r.pos - w, r.pos + w, lo[1], hi[1])
    for axis, roads in ((0, ru), (1, rv)):
        crossing = rv if axis == 0 else ru
        for r in roads:
            if r.median == 0 and not r.median_barrier:
                continue
            # median segments between intersections (and their stop lines)
            cuts = sorted(c.pos for c in crossing)
            hws = {c.pos: c.half_width + c.sidewalk + 3.0 for c in crossing}
            for p0, p1 in zip(cuts[:-1], cuts[1:]):
                a0, a1 = p0 + hws[p0], p1 - hws[p1]
                if a1 < lo[axis] or a0 > hi[axis]:
                    continue
                half = r.median / 2 if r.median > 0 else 0.2
                if axis == 0:
                    rect = (a0, a1, r.pos - half, r.pos + half)
                else:
                    rect = (r.pos - half, r.pos + half, a0, a1)
                if r.median > 0:
                    m.ground_rect(C.OTHER_FLAT, *rect, raised=1)
                else:
                    m.box(C.BARRIER, *rect, GROUND_Z, z_level(1.0))
    _street_furniture(m, rng, net, lo, hi)
    _round_corners(m, net, lo, hi)
    _hide_unobserved_ground(m, net, parked)
    return m, parked


def _hide_unobserved_ground(m: StaticMap, net: RoadNetwork, parked: StaticAgents) -> None:
    """Free the ground deeper than ``UNSEEN_DEPTH`` behind the nearest kerb, as Occ3D leaves the
    ground a car's LiDAR never reached unlabelled; keep it under anything standing on it."""
    uc = m.u0 + RES * (np.arange(m.ground.shape[0]) + 0.5)
    vc = m.v0 + RES * (np.arange(m.ground.shape[1]) + 0.5)
    d_u = np.min([np.abs(uc - r.pos) - r.half_width for r in net.roads[1]], axis=0)  # [H]
    d_v = np.min([np.abs(vc - r.pos) - r.half_width for r in net.roads[0]], axis=0)  # [W]
    unseen = (np.minimum(d_u[:, None], d_v[None, :]) > UNSEEN_DEPTH) & (m.obj == C.FREE)
    for (cu, cv), heading, (length, width, _) in zip(parked.centre, parked.heading, parked.size):
        eu, ev = (length / 2, width / 2) if heading[0] else (width / 2, length / 2)
        sl = m._slices(cu - eu, cu + eu, cv - ev, cv + ev)
        if sl is not None:
            unseen[sl] = False
    m.ground[unseen] = C.FREE
    m.ground_h[unseen] = 0
