"""One synthetic driving scene: town, traffic, ego drive, rendered 2 Hz frames.

``generate_scene(seed, num_frames)`` is a pure function of its arguments. Its
steps: a road network (``layout``), routes for the ego and for every other road
user (``routes``), a joint kinematic simulation with traffic lights, car
following and yielding (``motion``), the static town rasterised around the
ego's drive (``world``), and per frame the ego-frame label volume with agents
drawn in (``render``) plus its camera visibility mask (``visibility``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from t3fast.data import classes as C
from t3fast.data.synthetic import motion
from t3fast.data.synthetic.layout import RoadNetwork, make_network
from t3fast.data.synthetic.render import box_z, draw_boxes, render_static
from t3fast.data.synthetic.routes import make_route, random_start
from t3fast.data.synthetic.visibility import camera_mask
from t3fast.data.synthetic.world import StaticMap, build_static_map

#: label, length, width, height ranges (m), wished-speed range (m/s), max acceleration (m/s^2), share of traffic
VEHICLE_KINDS = (
    (C.CAR, (3.9, 5.0), (1.75, 2.05), (1.45, 1.9), (8.0, 13.0), 2.5, 0.62),
    (C.TRUCK, (6.5, 9.5), (2.4, 2.6), (2.8, 3.6), (6.0, 10.0), 1.5, 0.11),
    (C.BUS, (10.5, 12.5), (2.5, 2.9), (3.1, 3.5), (6.0, 10.0), 1.2, 0.06),
    (C.CONSTRUCTION_VEHICLE, (5.5, 7.5), (2.5, 2.9), (2.8, 3.5), (3.0, 6.0), 1.0, 0.04),
    (C.MOTORCYCLE, (1.9, 2.3), (0.7, 0.9), (1.3, 1.6), (9.0, 14.0), 3.5, 0.08),
    (C.BICYCLE, (1.6, 1.9), (0.5, 0.7), (1.5, 1.8), (3.0, 6.0), 1.2, 0.09),
)
TRAILER_SIZE = ((8.0, 12.0), (2.4, 2.6), (3.2, 3.8))
PEDESTRIAN_SIZE = ((0.5, 0.8), (0.5, 0.7), (1.5, 1.9))
RUNUP = 25.0  # m of path behind every spawn point (room for hitched trailers)
VIEW_MARGIN = 58.0  # m around the ego rasterised: half-diagonal of the 80 m grid plus a little


@dataclass
class SyntheticScene:
    """A generated scene of ``T`` frames with ``N`` agents (moving and parked, ego excluded).

    occ: uint8 ``[T, 200, 200, 16]`` ego-frame labels; mask_camera: bool ``[T, 200, 200, 16]``;
    ego_poses: float64 ``[T, 4, 4]`` ego -> world; boxes_world: float64 ``[T, N, 7]``
    (x, y, z, l, w, h, yaw) in world coordinates, yaw counter-clockwise from +x with the
    length along the heading; labels: int64 ``[N]``; ego_speed: ``[T]`` m/s.
    """

    seed: int
    occ: np.ndarray
    mask_camera: np.ndarray
    ego_poses: np.ndarray
    boxes_world: np.ndarray
    labels: np.ndarray
    ego_speed: np.ndarray


def _pose_matrix(x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    poses = np.zeros((len(x), 4, 4))
    c, s = np.cos(yaw), np.sin(yaw)
    poses[:, 0, 0], poses[:, 0, 1], poses[:, 1, 0], poses[:, 1, 1] = c, -s, s, c
    poses[:, 2, 2] = poses[:, 3, 3] = 1.0
    poses[:, 0, 3], poses[:, 1, 3] = x, y
    return poses


def world_to_ego(boxes: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World boxes ``[..., 7]`` into the ego frame of 4x4 ``pose`` (planar motion)."""
    out = boxes.copy()
    yaw = np.arctan2(pose[1, 0], pose[0, 0])
    dx, dy = boxes[..., 0] - pose[0, 3], boxes[..., 1] - pose[1, 3]
    c, s = np.cos(yaw), np.sin(yaw)
    out[..., 0] = c * dx + s * dy
    out[..., 1] = -s * dx + c * dy
    out[..., 2] = boxes[..., 2] - pose[2, 3]
    out[..., 6] = np.mod(boxes[..., 6] - yaw + np.pi, 2 * np.pi) - np.pi
    return out


@dataclass
class SceneWorld:
    """Everything about a scene before rendering: the town, its raster and the motion.

    ego_poses ``[T, 4, 4]``; boxes_world ``[T, N, 7]``; labels ``[N]``; ego_speed ``[T]``.
    """

    seed: int
    network: RoadNetwork
    static: StaticMap
    ego_poses: np.ndarray
    boxes_world: np.ndarray
    labels: np.ndarray
    ego_speed: np.ndarray


def generate_scene(seed: int, num_frames: int = 40) -> SyntheticScene:
    """Generate scene ``seed`` with ``num_frames`` 2 Hz frames (deterministic)."""
    return render_scene(simulate_scene(seed, num_frames))


def simulate_scene(seed: int, num_frames: int = 40) -> SceneWorld:
    """Lay out the town, simulate the traffic and rasterise the static world (no frames yet)."""
    rng = np.random.default_rng(seed)
    net = make_network(rng)
    steps = num_frames * motion.SUBSTEPS
    dt = C.FRAME_DT / motion.SUBSTEPS
    duration = num_frames * C.FRAME_DT

    # the ego: turns often, changes its wished speed every few seconds, sometimes stops
    cursor, _ = random_start(net, rng, np.zeros(2), 30.0, pedestrian=False, runup=RUNUP)
    ego_path = make_route(net, rng, cursor, RUNUP + 15.0 * duration + 40.0, False, (0.3, 0.3))
    paths = [ego_path]
    sizes = [(C.EGO_LENGTH, C.EGO_WIDTH, 1.7)]
    labels = [C.CAR]
    accel = [2.5]
    cruise = [motion.cruise_schedule(rng, steps, dt, rng.uniform(8.0, 13.0), (3.0, 8.0), 0.15)]
    pedestrian = [False]
    follows = [-1]
    hitch = [0.0]

    # other road users spawn around the part of town the ego can reach
    reach = ego_path.points[ego_path.s < RUNUP + 12.0 * duration]
    places = [ego_path.points[np.searchsorted(ego_path.s, RUNUP)]]
    n_vehicles = int(rng.integers(45, 75))
    n_pedestrians = int(rng.integers(40, 80))
    shares = np.array([k[-1] for k in VEHICLE_KINDS])
    # every kind once before drawing by share, and the first truck towing, so that each
    # scene has every agent class (a bus is 6 % of traffic and would be missing from many)
    first_kinds = list(rng.permutation(len(VEHICLE_KINDS)))
    towed = False
    for n, is_ped in ((n_vehicles, False), (n_pedestrians, True)):
        for _ in range(n):
            centre = reach[rng.integers(len(reach))]
            cur, place = random_start(net, rng, centre, 60.0, pedestrian=is_ped, runup=RUNUP)
            min_gap = 1.5 if is_ped else 14.0
            if min(np.linalg.norm(place - p) for p in places) < min_gap:
                continue
            places.append(place)
            path = make_route(net, rng, cur, RUNUP + 15.0 * duration + 20.0, is_ped,
                              (0.2, 0.2) if is_ped else (0.25, 0.25))
            if is_ped:
                (l0, l1), (w0, w1), (h0, h1) = PEDESTRIAN_SIZE
                label, speed, acc = C.PEDESTRIAN, rng.uniform(1.0, 1.6), 1.0
                schedule = motion.cruise_schedule(rng, steps, dt, speed, (4.0, 12.0), 0.1)
            else:
                kind = first_kinds.pop() if first_kinds else rng.choice(len(shares), p=shares)
                label, (l0, l1), (w0, w1), (h0, h1), (v0, v1), acc, _ = VEHICLE_KINDS[kind]
                schedule = motion.cruise_schedule(rng, steps, dt, rng.uniform(v0, v1), (4.0, 10.0), 0.05)
            paths.append(path)
            sizes.append((rng.uniform(l0, l1), rng.uniform(w0, w1), rng.uniform(h0, h1)))
            labels.append(label)
            accel.append(acc)
            cruise.append(schedule)
            pedestrian.append(is_ped)
            follows.append(-1)
            hitch.append(0.0)
            if label == C.TRUCK and (not towed or rng.random() < 0.5):  # tow a trailer
                towed = True
                (l0, l1), (w0, w1), (h0, h1) = TRAILER_SIZE
                size = (rng.uniform(l0, l1), rng.uniform(w0, w1), rng.uniform(h0, h1))
                paths.append(path)
                hitch.append(sizes[-1][0] / 2 + 1.0 + size[0] / 2)
                sizes.append(size)
                labels.append(C.TRAILER)
                accel.append(acc)
                cruise.append(schedule)
                pedestrian.append(False)
                follows.append(len(paths) - 2)

    size_arr = np.array(sizes)
    movers = motion.Movers(
        paths=paths,
        s0=np.full(len(paths), RUNUP) - np.array(hitch),
        length=size_arr[:, 0],
        width=size_arr[:, 1],
        accel=np.array(accel),
        cruise=np.stack(cruise, axis=1),
        pedestrian=np.array(pedestrian),
        follows=np.array(follows),
        hitch=np.array(hitch),
    )
    traj = motion.simulate(net, movers, num_frames, C.FRAME_DT)

    u, v = traj.position[..., 0], traj.position[..., 1]
    wx, wy = net.warp.to_world(u, v)
    yaw = net.warp.world_heading(u, traj.heading[..., 0], traj.heading[..., 1])
    ego_poses = _pose_matrix(wx[:, 0], wy[:, 0], yaw[:, 0])

    # rasterise the town around the drive, in town coordinates
    amp = net.warp.amplitude
    lo = np.array([wx[:, 0].min() - VIEW_MARGIN, wy[:, 0].min() - VIEW_MARGIN - 2 * amp])
    hi = np.array([wx[:, 0].max() + VIEW_MARGIN, wy[:, 0].max() + VIEW_MARGIN + 2 * amp])
    static, parked = build_static_map(net, rng, lo, hi)

    t_count = num_frames
    boxes = np.zeros((t_count, len(paths) - 1, 7))
    boxes[..., 0], boxes[..., 1], boxes[..., 6] = wx[:, 1:], wy[:, 1:], yaw[:, 1:]
    boxes[..., 3:6] = size_arr[1:]
    boxes[..., 2] = box_z(size_arr[1:, 2])
    if parked.label:
        centre = np.array(parked.centre)
        head = np.array(parked.heading)
        pw = np.zeros((len(centre), 7))
        pw[:, 0], pw[:, 1] = net.warp.to_world(centre[:, 0], centre[:, 1])
        pw[:, 6] = net.warp.world_heading(centre[:, 0], head[:, 0], head[:, 1])
        pw[:, 3:6] = np.array(parked.size)
        pw[:, 2] = box_z(pw[:, 5])
        boxes = np.concatenate([boxes, np.repeat(pw[None], t_count, 0)], axis=1)
        labels = labels + list(parked.label)
    return SceneWorld(seed, net, static, ego_poses, boxes, np.array(labels[1:], dtype=np.int64), traj.speed[:, 0])


def render_scene(world: SceneWorld) -> SyntheticScene:
    """Render every frame (labels with agents drawn in) and its camera visibility mask."""
    t_count = len(world.ego_poses)
    occ = np.empty((t_count, *C.GRID_SHAPE), dtype=np.uint8)
    mask = np.empty((t_count, *C.GRID_SHAPE), dtype=bool)
    for t in range(t_count):
        pose = world.ego_poses[t]
        vol = render_static(world.static, world.network.warp, ego_xy_yaw(pose))
        local = world_to_ego(world.boxes_world[t], pose)
        near = (np.abs(local[:, 0]) < 48.0) & (np.abs(local[:, 1]) < 48.0)
        draw_boxes(vol, local[near], world.labels[near])
        occ[t] = vol
        mask[t] = camera_mask(vol)
    return SyntheticScene(
        seed=world.seed,
        occ=occ,
        mask_camera=mask,
        ego_poses=world.ego_poses,
        boxes_world=world.boxes_world,
        labels=world.labels,
        ego_speed=world.ego_speed,
    )


def ego_xy_yaw(pose: np.ndarray) -> tuple[float, float, float]:
    """(x, y, yaw) of a planar 4x4 pose."""
    return float(pose[0, 3]), float(pose[1, 3]), float(np.arctan2(pose[1, 0], pose[0, 0]))
