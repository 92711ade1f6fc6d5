"""Routes through the road grid: lane-following paths for vehicles, sidewalk paths
for pedestrians, with turning arcs at intersections and the stop lines met on the way.

A route is a random walk on the grid. At each crossing road it goes straight or
turns left/right on a quarter circle. Everything is in town coordinates ``(u, v)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t3fast.data.synthetic.layout import STOP_LINE_MARGIN, Road, RoadNetwork

STEP = 0.5  # spacing of path samples (m)
#: lateral acceleration allowed in turns (m/s^2) and deceleration used to anticipate them
LATERAL_ACCEL = 2.0
ANTICIPATION_DECEL = 2.0


@dataclass
class Path:
    """A densely sampled route.

    points, tangents: ``[P, 2]`` town coordinates and unit directions; s: ``[P]`` arc length;
    speed_cap: ``[P]`` speed limit from curvature (m/s, ``inf`` on straights);
    stop_s, stop_axis, stop_inter: ``[K]`` arc length of each stop line (vehicles) or kerb
    (pedestrians on a crosswalk), the axis travelled when reaching it, and its intersection id.
    """

    points: np.ndarray
    tangents: np.ndarray
    s: np.ndarray
    speed_cap: np.ndarray
    stop_s: np.ndarray
    stop_axis: np.ndarray
    stop_inter: np.ndarray

    @property
    def length(self) -> float:
        return float(self.s[-1])


def _side(axis: int) -> float:
    """Sign that maps 'offset to the right of travel' to the across coordinate."""
    return -1.0 if axis == 0 else 1.0


def _to_uv(axis: int, along: np.ndarray, across: np.ndarray) -> np.ndarray:
    return np.stack([along, across], -1) if axis == 0 else np.stack([across, along], -1)


def _unit(axis: int, sigma: float) -> np.ndarray:
    return np.array([sigma, 0.0]) if axis == 0 else np.array([0.0, sigma])


@dataclass
class _Cursor:
    axis: int
    road: int  # index into network.roads[axis]
    sigma: float  # +1 / -1 along the road's axis
    across: float  # across coordinate of the followed line
    along: float  # current along coordinate


def _line_across(road: Road, sigma: float, offset: float) -> float:
    return road.pos + _side(road.axis) * sigma * offset


def make_route(
    network: RoadNetwork,
    rng: np.random.Generator,
    start: _Cursor,
    length: float,
    pedestrian: bool,
    turn_probs: tuple[float, float] = (0.25, 0.25),
) -> Path:
    """Walk ``length`` metres from ``start``; ``turn_probs`` = P(left), P(right) per crossing."""
    pts: list[np.ndarray] = []
    tans: list[np.ndarray] = []
    arcs: list[tuple[float, float, float]] = []
    stops: list[tuple[float, int, int]] = []
    cur = start
    travelled = 0.0

    def add_straight(a0: float, a1: float) -> None:
        nonlocal travelled
        n = max(int(abs(a1 - a0) / STEP), 1)
        along = a0 + (a1 - a0) * np.arange(n) / n
        pts.append(_to_uv(cur.axis, along, np.full(n, cur.across)))
        tans.append(np.repeat(_unit(cur.axis, cur.sigma)[None], n, 0))
        travelled += abs(a1 - a0)

    while travelled < length:
        others = network.roads[1 - cur.axis]
        ahead = [i for i, r in enumerate(others) if cur.sigma * (r.pos - cur.along) > 1.0]
        ahead.sort(key=lambda i: cur.sigma * (others[i].pos - cur.along))
        if not ahead:  # left the town: run straight out
            add_straight(cur.along, cur.along + cur.sigma * (length - travelled + STEP))
            break
        ci = ahead[0]
        cross = others[ci]
        road_u, road_v = (cur.road, ci) if cur.axis == 0 else (ci, cur.road)
        inter = network.intersection_id(road_u, road_v)
        pick = rng.random()
        turn = "left" if pick < turn_probs[0] else "right" if pick < sum(turn_probs) else "straight"
        # heading after the turn, as a sign along the crossing road's axis
        left_sign = cur.sigma if cur.axis == 0 else -cur.sigma
        new_sigma = left_sign if turn == "left" else -left_sign
        if pedestrian:
            radius = 1.0
            # near sidewalk line of the crossing road
            corner_along = cross.pos - cur.sigma * (cross.half_width + cross.sidewalk / 2)
        else:
            radius = 6.0 if turn == "right" else 9.0
            lane = cross.lanes - 1 if turn == "right" else 0
            corner_along = _line_across(cross, new_sigma, cross.lane_offset(lane))
        room = cur.sigma * (corner_along - cur.along)
        if turn != "straight" and room > radius + STEP:
            arc_start = corner_along - cur.sigma * radius
            add_straight(cur.along, arc_start)
            if not pedestrian:
                s_cross = travelled + radius + cur.sigma * (cross.pos - corner_along)
                stops.append((s_cross - cross.half_width - STOP_LINE_MARGIN, cur.axis, inter))
            h0 = _unit(cur.axis, cur.sigma)
            h1 = _unit(cross.axis, new_sigma)
            s0 = _to_uv(cur.axis, np.array([arc_start]), np.array([cur.across]))[0]
            phi = np.linspace(0.0, np.pi / 2, max(int(np.pi / 2 * radius / STEP), 2), endpoint=False)
            pts.append(s0 + radius * np.sin(phi)[:, None] * h0 + radius * (1 - np.cos(phi))[:, None] * h1)
            tans.append(np.cos(phi)[:, None] * h0 + np.sin(phi)[:, None] * h1)
            if not pedestrian:
                arcs.append((travelled, travelled + np.pi / 2 * radius, float(np.sqrt(LATERAL_ACCEL * radius))))
            travelled += np.pi / 2 * radius
            # the new line lies at the corner; its along axis is the old across axis
            exit_along = cur.across + new_sigma * radius
            cur = _Cursor(axis=cross.axis, road=ci, sigma=new_sigma, across=corner_along, along=exit_along)
        else:
            # straight over the crossing road; stop line (vehicles) or kerb (pedestrians) before it
            target = cross.pos + cur.sigma * (cross.half_width + 2.0)
            s_cross = travelled + abs(cross.pos - cur.along)
            margin = 0.4 if pedestrian else STOP_LINE_MARGIN
            stops.append((s_cross - cross.half_width - margin, cur.axis, inter))
            add_straight(cur.along, target)
            cur = _Cursor(cur.axis, cur.road, cur.sigma, cur.across, target)

    points = np.concatenate(pts)
    tangents = np.concatenate(tans)
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    cap = np.full(len(s), np.inf)
    for s_a, s_b, v_a in arcs:
        before = np.sqrt(v_a**2 + 2 * ANTICIPATION_DECEL * np.clip(s_a - s, 0.0, None))
        cap = np.minimum(cap, np.where(s <= s_b, before, np.inf))
    stop_arr = np.array(stops, dtype=np.float64).reshape(-1, 3)
    return Path(
        points=points,
        tangents=tangents,
        s=s,
        speed_cap=cap,
        stop_s=stop_arr[:, 0],
        stop_axis=stop_arr[:, 1].astype(np.int64),
        stop_inter=stop_arr[:, 2].astype(np.int64),
    )


def random_start(
    network: RoadNetwork,
    rng: np.random.Generator,
    centre: np.ndarray,
    radius: float,
    pedestrian: bool,
    runup: float,
) -> tuple[_Cursor, np.ndarray]:
    """A random place on a lane (or sidewalk) within ``radius`` of ``centre`` (town coords).

    The returned cursor starts ``runup`` metres behind that place, so followers
    (trailers) have path behind them; also returns the place itself.
    """
    while True:
        axis = int(rng.integers(2))
        roads = network.roads[axis]
        across_c = centre[1 - axis]
        near = [i for i, r in enumerate(roads) if abs(r.pos - across_c) < radius]
        if not near:
            continue
        ri = int(rng.choice(near))
        road = roads[ri]
        sigma = float(rng.choice([-1.0, 1.0]))
        if pedestrian:
            offset = road.half_width + road.sidewalk / 2
            across = road.pos + float(rng.choice([-1.0, 1.0])) * offset
        else:
            across = _line_across(road, sigma, road.lane_offset(int(rng.integers(road.lanes))))
        along = centre[axis] + rng.uniform(-radius, radius)
        # not inside an intersection: keep clear of crossing carriageways
        crossing = network.roads[1 - axis]
        if any(abs(along - r.pos) < r.half_width + (2.0 if pedestrian else 10.0) for r in crossing):
            continue
        place = _to_uv(axis, np.array([along]), np.array([across]))[0]
        return _Cursor(axis, ri, sigma, across, along - sigma * runup), place
