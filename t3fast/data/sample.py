"""The sample structure shared by every driving dataset, windows, flips and collation.

A sample is 11 consecutive 2 Hz frames: indices 0..3 are the past, 4 is the
present (the "current" frame), 5..10 the future (3 s).

* ``occ`` uint8 ``[11, 200, 200, 16]`` and ``mask_camera`` bool ``[11, 200, 200, 16]``:
  each frame in its own ego frame, as in Occ3D (x forward, y left, z up; see
  ``t3fast.data.classes``).
* ``past_actions`` float32 ``[4, 2]`` (frame 0->1, ..., 3->4) and ``future_actions``
  float32 ``[6, 2]`` (4->5, ..., 9->10): the ego displacement (dx, dy) in metres
  between consecutive frames, ALL expressed in the present frame's ego
  coordinates, like nuScenes/UniAD ``gt_ego_fut_trajs``. The planned trajectory
  is ``future_actions.cumsum(0)``; the ego is at the origin in the present frame.
* ``boxes`` float32 ``[11, A, 7]``: per frame, agent boxes (x, y, z, l, w, h, yaw)
  in the PRESENT frame's coordinates (z is the box centre, yaw counter-clockwise
  from +x with the length along the heading); ``box_valid`` bool ``[11, A]`` says
  which agent is annotated in which frame (centre inside the 80 m grid);
  ``box_labels`` int64 ``[A]`` Occ3D class ids.
* ``ego_poses`` float32 ``[11, 4, 4]``: ego -> world per frame.
* ``command`` int64 ``[]``: the route command of the present frame (``t3fast.data.route``:
  turn right / turn left / go straight; it looks 3 s ahead).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from t3fast.data.route import mirror_command, route_command

NUM_PAST = 4
NUM_FUTURE = 6
WINDOW = NUM_PAST + 1 + NUM_FUTURE  # 11 frames
PRESENT = NUM_PAST  # index of the present frame in a window


@dataclass
class DrivingSample:
    """One 11-frame window (see the module docstring for the fields and frames)."""

    occ: torch.Tensor
    mask_camera: torch.Tensor
    past_actions: torch.Tensor
    future_actions: torch.Tensor
    boxes: torch.Tensor
    box_valid: torch.Tensor
    box_labels: torch.Tensor
    ego_poses: torch.Tensor
    command: torch.Tensor
    scene: str
    start: int  # index in its scene of the window's first frame

    @property
    def past_occ(self) -> torch.Tensor:
        """Frames 0..4 (past and present), ``[5, 200, 200, 16]``."""
        return self.occ[: PRESENT + 1]

    @property
    def future_occ(self) -> torch.Tensor:
        """Frames 5..10, ``[6, 200, 200, 16]``."""
        return self.occ[PRESENT + 1 :]

    @property
    def trajectory(self) -> torch.Tensor:
        """Future ego positions in the present frame, ``[6, 2]``."""
        return self.future_actions.cumsum(0)


@dataclass
class DrivingBatch:
    """Collated samples: every tensor field gains a leading batch dim ``B``; the agent
    dim is padded to the largest ``A`` in the batch (padding has ``box_valid`` False
    and label ``-1``)."""

    occ: torch.Tensor
    mask_camera: torch.Tensor
    past_actions: torch.Tensor
    future_actions: torch.Tensor
    boxes: torch.Tensor
    box_valid: torch.Tensor
    box_labels: torch.Tensor
    ego_poses: torch.Tensor
    command: torch.Tensor  # [B]
    scene: list[str]
    start: list[int]

    @property
    def past_occ(self) -> torch.Tensor:
        return self.occ[:, : PRESENT + 1]

    @property
    def future_occ(self) -> torch.Tensor:
        return self.occ[:, PRESENT + 1 :]

    def to(self, device: torch.device | str) -> DrivingBatch:
        return replace(
            self, **{f.name: getattr(self, f.name).to(device) for f in fields(self) if f.name not in ("scene", "start")}
        )


def collate_samples(samples: list[DrivingSample]) -> DrivingBatch:
    """Stack samples into a ``DrivingBatch``, padding the agent dimension."""
    a_max = max(s.box_labels.shape[0] for s in samples)
    b, device = len(samples), samples[0].boxes.device
    boxes = torch.zeros(b, WINDOW, a_max, 7, device=device)
    valid = torch.zeros(b, WINDOW, a_max, dtype=torch.bool, device=device)
    labels = torch.full((b, a_max), -1, dtype=torch.int64, device=device)
    for k, s in enumerate(samples):
        a = s.box_labels.shape[0]
        boxes[k, :, :a] = s.boxes
        valid[k, :, :a] = s.box_valid
        labels[k, :a] = s.box_labels
    return DrivingBatch(
        occ=torch.stack([s.occ for s in samples]),
        mask_camera=torch.stack([s.mask_camera for s in samples]),
        past_actions=torch.stack([s.past_actions for s in samples]),
        future_actions=torch.stack([s.future_actions for s in samples]),
        boxes=boxes,
        box_valid=valid,
        box_labels=labels,
        ego_poses=torch.stack([s.ego_poses for s in samples]),
        command=torch.stack([s.command for s in samples]),
        scene=[s.scene for s in samples],
        start=[s.start for s in samples],
    )


def window_starts(num_frames: int, stride: int) -> list[int]:
    """First-frame indices of the 11-frame windows of a scene of ``num_frames`` frames."""
    return list(range(0, num_frames - WINDOW + 1, stride))


def relative_poses(ego_poses: np.ndarray, reference: int) -> np.ndarray:
    """``inv(pose[reference]) @ pose[t]`` for every t: frame t -> frame ``reference``, ``[T, 4, 4]``."""
    return np.linalg.inv(ego_poses[reference])[None] @ ego_poses


def actions_from_poses(ego_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Past ``[4, 2]`` and future ``[6, 2]`` actions of an 11-frame window from its poses ``[11, 4, 4]``."""
    xy = relative_poses(ego_poses, PRESENT)[:, :2, 3]
    steps = np.diff(xy, axis=0)
    return steps[:PRESENT], steps[PRESENT:]


def boxes_to_frame(boxes: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Apply a planar rigid ``transform`` (4x4, source -> target frame) to boxes ``[..., 7]``."""
    out = np.array(boxes, dtype=np.float64, copy=True)
    rot = np.arctan2(transform[1, 0], transform[0, 0])
    x, y = boxes[..., 0], boxes[..., 1]
    out[..., 0] = transform[0, 0] * x + transform[0, 1] * y + transform[0, 3]
    out[..., 1] = transform[1, 0] * x + transform[1, 1] * y + transform[1, 3]
    out[..., 2] = boxes[..., 2] + transform[2, 3]
    out[..., 6] = np.mod(boxes[..., 6] + rot + np.pi, 2 * np.pi) - np.pi
    return out


def build_sample(
    occ: np.ndarray,
    mask_camera: np.ndarray,
    ego_poses: np.ndarray,
    boxes: np.ndarray,
    box_valid: np.ndarray,
    box_labels: np.ndarray,
    scene: str,
    start: int,
    future_actions: np.ndarray | None = None,
    command: int | None = None,
) -> DrivingSample:
    """Assemble a sample from one window of a scene.

    occ, mask_camera: ``[11, 200, 200, 16]``; ego_poses: ``[11, 4, 4]``;
    boxes: ``[11, A, 7]`` with each frame's boxes in THAT frame's ego coordinates,
    box_valid ``[11, A]``, box_labels ``[A]``. Agents never valid in the window are
    dropped; boxes are moved into the present frame. ``future_actions`` overrides
    the future actions computed from the poses (Occ3D: ``gt_ego_fut_trajs``); ``command``
    the route command derived from the future actions (:func:`~t3fast.data.route.route_command`;
    Occ3D: ``gt_ego_fut_cmd``).
    """
    keep = box_valid.any(axis=0)
    boxes, box_valid, box_labels = boxes[:, keep], box_valid[:, keep], box_labels[keep]
    rel = relative_poses(ego_poses, PRESENT)
    present_boxes = np.stack([boxes_to_frame(boxes[t], rel[t]) for t in range(WINDOW)]) if keep.any() else (
        np.zeros((WINDOW, 0, 7))
    )
    present_boxes[~box_valid] = 0.0
    past, fut = actions_from_poses(ego_poses)
    if future_actions is not None:
        fut = future_actions
    fut = np.asarray(fut, dtype=np.float32)
    if command is None:
        command = int(route_command(torch.from_numpy(fut)))
    return DrivingSample(
        occ=torch.from_numpy(np.ascontiguousarray(occ, dtype=np.uint8)),
        mask_camera=torch.from_numpy(np.ascontiguousarray(mask_camera, dtype=bool)),
        past_actions=torch.from_numpy(past.astype(np.float32)),
        future_actions=torch.from_numpy(fut),
        boxes=torch.from_numpy(present_boxes.astype(np.float32)),
        box_valid=torch.from_numpy(box_valid.astype(bool)),
        box_labels=torch.from_numpy(box_labels.astype(np.int64)),
        ego_poses=torch.from_numpy(ego_poses.astype(np.float32)),
        command=torch.tensor(command, dtype=torch.int64),
        scene=scene,
        start=start,
    )


_FLIP = {"x": 0, "y": 1}


def flip_sample(sample: DrivingSample, axis: str) -> DrivingSample:
    """Mirror a sample across the ego's x axis (``axis="y"``: y -> -y) or y axis (``"x"``: x -> -x).

    Applied consistently to occupancy and masks (every frame), actions, boxes
    (position and yaw), poses (the world is mirrored with the ego: pose -> F pose F) and the
    route command (mirrored left-right, a left turn is a right one).
    """
    k = _FLIP[axis]
    occ = sample.occ.flip(k + 1)
    mask = sample.mask_camera.flip(k + 1)
    sign = torch.ones(2)
    sign[k] = -1.0
    boxes = sample.boxes.clone()
    boxes[..., k] = -boxes[..., k]
    yaw = boxes[..., 6]
    mirrored = -yaw if axis == "y" else torch.pi - yaw
    boxes[..., 6] = torch.remainder(mirrored + torch.pi, 2 * torch.pi) - torch.pi
    boxes[~sample.box_valid] = 0.0
    f = torch.diag(torch.tensor([1.0, 1.0, 1.0, 1.0]))
    f[k, k] = -1.0
    return replace(
        sample,
        occ=occ,
        mask_camera=mask,
        past_actions=sample.past_actions * sign,
        future_actions=sample.future_actions * sign,
        boxes=boxes,
        ego_poses=f @ sample.ego_poses @ f,
        command=mirror_command(sample.command) if axis == "y" else sample.command,
    )


def random_flip(sample: DrivingSample, generator: torch.Generator | None = None, p: float = 0.5) -> DrivingSample:
    """Flip along x and along y, each with probability ``p``."""
    for axis in ("x", "y"):
        if torch.rand((), generator=generator).item() < p:
            sample = flip_sample(sample, axis)
    return sample


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """BEV corners ``[..., 4, 2]`` of boxes ``[..., 7]`` (front-left, front-right, rear-right, rear-left)."""
    c, s = np.cos(boxes[..., 6]), np.sin(boxes[..., 6])
    hl, hw = boxes[..., 3] / 2, boxes[..., 4] / 2
    local = np.stack([np.stack([hl, hw], -1), np.stack([hl, -hw], -1), np.stack([-hl, -hw], -1),
                      np.stack([-hl, hw], -1)], -2)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # [..., 2, 2]
    return np.einsum("...ij,...kj->...ki", rot, local) + boxes[..., None, :2]


__all__ = [
    "DrivingBatch",
    "DrivingSample",
    "NUM_FUTURE",
    "NUM_PAST",
    "PRESENT",
    "WINDOW",
    "actions_from_poses",
    "box_corners",
    "boxes_to_frame",
    "build_sample",
    "collate_samples",
    "flip_sample",
    "random_flip",
    "relative_poses",
    "window_starts",
]
