"""Kinematic motion of all road users along their paths, simulated together.

Each mover has a path (``routes.Path``) and advances its arc length ``s`` with a
speed that tracks the lowest of: its own (changing) cruise speed, the curvature
limit of the path ahead, the speed that still stops behind the nearest road user
ahead, and the speed that still stops at a red light. Acceleration is bounded.
The whole population is stepped at once (vectorised over movers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t3fast.data.synthetic.layout import RoadNetwork
from t3fast.data.synthetic.routes import Path

SUBSTEPS = 5  # simulation steps per 2 Hz frame
TRACKING_TIME = 0.7  # s, time constant of the speed controller
COMFORT_DECEL = 2.5  # m/s^2, used to plan stops
MAX_DECEL = 6.0  # m/s^2, hard limit; a light that needs more is run (amber)


@dataclass
class Movers:
    """Per-mover parameters, all arrays ``[N]`` except ``cruise`` ``[steps, N]``.

    ``pedestrian`` movers only yield to pedestrians; vehicles yield to everybody.
    ``follows[i] = j`` makes mover i a trailer hitched ``hitch[i]`` metres behind j.
    """

    paths: list[Path]
    s0: np.ndarray
    length: np.ndarray
    width: np.ndarray
    accel: np.ndarray
    cruise: np.ndarray
    pedestrian: np.ndarray
    follows: np.ndarray
    hitch: np.ndarray


@dataclass
class Trajectories:
    """Town-coordinate positions ``[T, N, 2]``, unit headings ``[T, N, 2]``, speeds ``[T, N]``."""

    position: np.ndarray
    heading: np.ndarray
    speed: np.ndarray


class _PathTable:
    """All paths concatenated so that one ``np.interp`` serves every mover."""

    def __init__(self, paths: list[Path]):
        offsets, total = [], 0.0
        for p in paths:
            offsets.append(total)
            total += p.length + 10.0  # gap keeps the concatenated abscissa increasing
        self.offset = np.array(offsets)
        self.length = np.array([p.length for p in paths])
        self.xp = np.concatenate([p.s + o for p, o in zip(paths, offsets)])
        self.points = np.concatenate([p.points for p in paths])
        self.tangents = np.concatenate([p.tangents for p in paths])
        self.cap = np.concatenate([p.speed_cap for p in paths])

    def lookup(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.clip(s, 0.0, self.length) + self.offset
        pos = np.stack([np.interp(q, self.xp, self.points[:, k]) for k in range(2)], -1)
        tan = np.stack([np.interp(q, self.xp, self.tangents[:, k]) for k in range(2)], -1)
        tan /= np.maximum(np.linalg.norm(tan, axis=1, keepdims=True), 1e-9)
        cap = np.interp(q, self.xp, np.where(np.isinf(self.cap), 1e3, self.cap))
        return pos, tan, cap


def simulate(network: RoadNetwork, movers: Movers, num_frames: int, frame_dt: float) -> Trajectories:
    """Step all movers for ``num_frames`` frames of ``frame_dt`` seconds; record each frame."""
    n = len(movers.paths)
    table = _PathTable(movers.paths)
    dt = frame_dt / SUBSTEPS
    kmax = max(len(p.stop_s) for p in movers.paths) or 1
    stop_s = np.full((n, kmax), np.inf)
    stop_axis = np.zeros((n, kmax), dtype=np.int64)
    stop_inter = np.zeros((n, kmax), dtype=np.int64)
    for i, p in enumerate(movers.paths):
        stop_s[i, : len(p.stop_s)] = p.stop_s
        stop_axis[i, : len(p.stop_s)] = p.stop_axis
        stop_inter[i, : len(p.stop_s)] = p.stop_inter

    hitched = movers.follows >= 0
    # who yields to whom: vehicles to all, pedestrians to pedestrians; never to oneself or one's trailer/truck
    yields = ~movers.pedestrian[:, None] | movers.pedestrian[None, :]
    np.fill_diagonal(yields, False)
    for i in np.flatnonzero(hitched):
        yields[i, movers.follows[i]] = yields[movers.follows[i], i] = False
    standstill_gap = np.where(movers.pedestrian, 0.4, 2.0)
    lateral_margin = np.where(movers.pedestrian, 0.2, 0.6)

    s = movers.s0.astype(np.float64).copy()
    v = np.zeros(n)
    v[:] = movers.cruise[0] * 0.8  # start already moving, as a scene cut from a longer drive
    out_pos, out_head, out_speed = [], [], []
    for step in range(num_frames * SUBSTEPS):
        t = step * dt
        s[hitched] = s[movers.follows[hitched]] - movers.hitch[hitched]
        v[hitched] = v[movers.follows[hitched]]
        pos, tan, cap = table.lookup(s)
        if step % SUBSTEPS == 0:
            out_pos.append(pos)
            out_head.append(tan)
            out_speed.append(v.copy())

        # nearest road user ahead in one's own corridor
        rel = pos[None, :, :] - pos[:, None, :]  # [i, j] = pos_j - pos_i
        along = np.einsum("ijk,ik->ij", rel, tan)
        lateral = np.abs(rel[..., 0] * tan[:, None, 1] - rel[..., 1] * tan[:, None, 0])
        corridor = (movers.width[:, None] + movers.width[None, :]) / 2 + lateral_margin[:, None]
        ahead = yields & (along > 0) & (lateral < corridor) & (along < 60.0)
        ahead &= ~(ahead & ahead.T & (np.arange(n)[:, None] < np.arange(n)[None, :]))  # lower index goes first
        gap = along - (movers.length[:, None] + movers.length[None, :]) / 2
        d_lead = np.min(np.where(ahead, gap, np.inf), axis=1)
        v_follow = np.sqrt(2 * COMFORT_DECEL * np.clip(d_lead - standstill_gap, 0.0, None))

        # red lights: stop before the line unless that would need more than MAX_DECEL
        front = s + np.where(movers.pedestrian, 0.0, movers.length / 2)
        d_stop = stop_s - front[:, None]
        red = ~network.green(stop_inter, stop_axis, t) & np.isfinite(stop_s)
        can_stop = v[:, None] ** 2 < 2 * MAX_DECEL * np.clip(d_stop, 1e-3, None)
        relevant = red & (d_stop > -0.5) & can_stop
        d_light = np.min(np.where(relevant, d_stop, np.inf), axis=1)
        v_light = np.sqrt(2 * COMFORT_DECEL * np.clip(d_light - 0.3, 0.0, None))

        target = np.minimum.reduce([movers.cruise[min(step, len(movers.cruise) - 1)], cap, v_follow, v_light])
        a = np.clip((target - v) / TRACKING_TIME, -MAX_DECEL, movers.accel)
        v = np.clip(v + a * dt, 0.0, None)
        s = s + v * dt
    return Trajectories(np.stack(out_pos), np.stack(out_head), np.stack(out_speed))


def cruise_schedule(
    rng: np.random.Generator, steps: int, dt: float, base: float, change_every: tuple[float, float], stop_prob: float
) -> np.ndarray:
    """Piecewise-constant wished speed ``[steps]``: changes every few seconds, sometimes to a stop."""
    out = np.empty(steps)
    i = 0
    while i < steps:
        n = int(rng.uniform(*change_every) / dt)
        speed = 0.0 if rng.random() < stop_prob else base * rng.uniform(0.45, 1.25)
        out[i : i + n] = speed
        i += n
    return out
