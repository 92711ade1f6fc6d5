"""Road network of a synthetic town: a grid of roads bent into curves.

The town is laid out in straight "town coordinates" ``(u, v)``: roads run along
u (at a constant v) or along v (at a constant u). World coordinates bend the
roads that run along u into gentle curves with one closed-form shear,

    x = u,   y = v + amplitude * sin(2 pi u / wavelength + phase),

so lane following and rasterisation stay simple in ``(u, v)`` while the world,
and therefore what the ego sees, has curved roads. All distances are metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LANE_WIDTH = 3.5
#: distance from the centre of the crossing road to a vehicle's stop line, beyond its half width
STOP_LINE_MARGIN = 4.0


@dataclass(frozen=True)
class Road:
    """One straight road of the grid in town coordinates.

    ``axis`` 0: the road runs along u at ``v = pos``; ``axis`` 1: along v at ``u = pos``.
    """

    axis: int
    pos: float
    lanes: int  # lanes per direction
    median: float  # width of the raised central island (0: painted line)
    sidewalk: float  # sidewalk width on each side
    median_barrier: bool

    @property
    def half_width(self) -> float:
        """Half the width of the carriageway (kerb to kerb)."""
        return self.median / 2 + self.lanes * LANE_WIDTH

    def lane_offset(self, lane: int) -> float:
        """Distance of lane ``lane`` (0 = next to the centre) from the road centre."""
        return self.median / 2 + (lane + 0.5) * LANE_WIDTH


@dataclass(frozen=True)
class Warp:
    """The shear that bends roads running along u: ``y = v + a sin(k u + phase)``."""

    amplitude: float
    wavenumber: float
    phase: float

    def to_world(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return u, v + self.amplitude * np.sin(self.wavenumber * u + self.phase)

    def to_town(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x, y - self.amplitude * np.sin(self.wavenumber * x + self.phase)

    def world_heading(self, u: np.ndarray, hu: np.ndarray, hv: np.ndarray) -> np.ndarray:
        """World yaw of a town-coordinate direction ``(hu, hv)`` taken at ``u``."""
        slope = self.amplitude * self.wavenumber * np.cos(self.wavenumber * u + self.phase)
        return np.arctan2(hv + slope * hu, hu)


@dataclass(frozen=True)
class RoadNetwork:
    """Roads along u (``roads[0]``, sorted by v) and along v (``roads[1]``, sorted by u)."""

    roads: tuple[tuple[Road, ...], tuple[Road, ...]]
    warp: Warp
    light_offsets: np.ndarray  # [n_roads_u, n_roads_v] traffic-light phase offsets, seconds
    light_cycle: float

    def intersection_id(self, road_u: int, road_v: int) -> int:
        return road_u * len(self.roads[1]) + road_v

    def green(self, intersection: np.ndarray, axis: np.ndarray, t: float) -> np.ndarray:
        """Whether traffic travelling along ``axis`` may enter ``intersection`` at time ``t``.

        Each cycle gives the first half to axis 0 and the second half to axis 1,
        the last 2 s of each half being amber/all-red.
        """
        phase = np.mod(t + self.light_offsets.reshape(-1)[intersection], self.light_cycle)
        half = self.light_cycle / 2
        local = np.where(axis == 0, phase, phase - half)
        return (local >= 0) & (local < half - 2.0)


def make_network(rng: np.random.Generator, extent: float = 450.0) -> RoadNetwork:
    """A random road grid covering ``[-extent, extent]^2`` around the origin."""
    roads: list[tuple[Road, ...]] = []
    for axis in (0, 1):
        positions = [rng.uniform(-10.0, 10.0)]
        while positions[-1] < extent:
            positions.append(positions[-1] + rng.uniform(55.0, 95.0))
        while positions[0] > -extent:
            positions.insert(0, positions[0] - rng.uniform(55.0, 95.0))
        axis_roads = []
        for pos in positions:
            lanes = int(rng.choice([1, 2], p=[0.55, 0.45]))
            median = float(rng.choice([0.0, 2.0])) if lanes == 2 else 0.0
            axis_roads.append(
                Road(
                    axis=axis,
                    pos=float(pos),
                    lanes=lanes,
                    median=median,
                    sidewalk=float(rng.uniform(2.2, 4.0)),
                    median_barrier=bool(median == 0.0 and lanes == 2 and rng.random() < 0.5),
                )
            )
        roads.append(tuple(axis_roads))
    warp = Warp(
        amplitude=float(rng.uniform(2.0, 9.0)),
        wavenumber=float(2 * np.pi / rng.uniform(220.0, 380.0)),
        phase=float(rng.uniform(0, 2 * np.pi)),
    )
    cycle = float(rng.uniform(18.0, 26.0))
    offsets = rng.uniform(0.0, cycle, size=(len(roads[0]), len(roads[1])))
    return RoadNetwork(roads=(roads[0], roads[1]), warp=warp, light_offsets=offsets, light_cycle=cycle)
