"""Stage 1: the past frames into triplanes, in the frame the forecaster works in.

Ego motion is geometry: an ego-aligned model moves every past frame into the present ego frame
with its pose before encoding (:func:`~t3fast.models.ego_motion.warp_sequence`), so static
content stands still and the forecaster's job is what moves; the papers' formulation encodes
every frame in its own ego frame and leaves the ego's motion to the forecaster."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.forecast.records import Past
from t3fast.host_syncs import reads_host
from t3fast.models.ego_motion import planar_poses, warp_sequence
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.triplane import Triplane


def split_past_motion(motion: Tensor) -> tuple[Tensor, Tensor]:
    """Past planar poses ``[B, T, 3]`` (present frame, present last) and displacements
    ``[B, T - 1, 2]`` from either ego -> world poses ``[B, T, 4, 4]`` or past displacements
    ``[B, T - 1, 2]`` (then each past heading is taken as the direction of travel)."""
    if motion.dim() == 4 and motion.shape[-2:] == (4, 4):
        poses = planar_poses(motion, motion.shape[1] - 1)
        return poses, poses[:, 1:, :2] - poses[:, :-1, :2]
    if motion.dim() != 3 or motion.shape[-1] != 2:
        raise ValueError(f"past motion must be poses [B, T, 4, 4] or displacements [B, T-1, 2], "
                         f"got shape {list(motion.shape)}")
    # positions of the past frames: the present at the origin, each earlier one a step back
    back = torch.flip(torch.flip(motion, [1]).cumsum(1), [1])
    xy = torch.cat([-back, torch.zeros_like(motion[:, :1])], dim=1)
    heading = torch.atan2(motion[..., 1], motion[..., 0])
    heading = torch.cat([heading[:, :1], heading], dim=1) - heading[:, -1:]  # the present heads along +x
    return torch.cat([xy, heading.unsqueeze(-1)], dim=-1), motion


#: frames an accelerator encodes in one call: a batch of 64 windows' 5 past frames in 10 calls,
#: each full-resolution activation of the small encoder 0.6 GB (2.6 GB for the paper's)
FRAMES_PER_CALL = 32


@torch.no_grad()
def encode_sequence(encoder: TriplaneEncoder, occupancy: Tensor, frame_by_frame: bool | None = None) -> Triplane:
    """Labels ``[B, T, X, Y, Z]`` -> triplane planes ``[B, T, C, H, W]`` (the frozen encoder).

    ``frame_by_frame`` (default: on the CPU): a time step per call, whose full-resolution
    activations (20 MB a frame) come from the C allocator's heap, where five frames' (100 MB)
    would be mapped afresh at every call, page faults and all (a third of the CPU encoding time
    at batch 1). On the CPU's own path (:func:`~t3fast.host_syncs.reads_host`; not the GPU's code
    under ``sync_free``, which keeps a GPU's batching) each window's frame alone, too: its
    activations then stay in the last-level cache from layer to layer, where a batch's stream
    through memory at every layer (4 windows' past frames: 1.9 s in a call per time step,
    0.6-0.85 s a frame per call, on 2 cores). On an accelerator up to :data:`FRAMES_PER_CALL`
    frames in one call: a launch per layer, not per frame and layer."""
    if frame_by_frame is None:
        frame_by_frame = occupancy.device.type == "cpu"
    b, t = occupancy.shape[:2]
    if frame_by_frame:
        windows = occupancy.split(1) if reads_host(occupancy.device) else [occupancy]
        return Triplane.cat([Triplane.stack([encoder(w[:, i]) for i in range(t)]) for w in windows])
    parts = Triplane.cat([encoder(frames) for frames in occupancy.flatten(0, 1).split(FRAMES_PER_CALL)])
    return parts.map(lambda p: p.unflatten(0, (b, t)))


class EncodePast:
    """Past labels and ego motion -> :class:`Past`.

    Args:
        encoder: the frozen triplane encoder.
        ego_aligned: encode every frame in the present ego frame; False: each in its own.
    """

    def __init__(self, encoder: TriplaneEncoder, ego_aligned: bool):
        self.encoder, self.ego_aligned = encoder, ego_aligned

    @torch.no_grad()
    def planes(self, occupancy: Tensor, poses: Tensor) -> Triplane:
        """Past frames ``[B, T, X, Y, Z]`` with planar poses ``[B, T, 3]`` (present frame) ->
        planes ``[B, T, C, H, W]`` in the forecaster's frame."""
        if self.ego_aligned:
            occupancy = warp_sequence(occupancy, poses)
        return encode_sequence(self.encoder, occupancy)

    def __call__(self, occupancy: Tensor, motion: Tensor) -> Past:
        """``occupancy`` ``[B, T, X, Y, Z]`` and ``motion`` (ego -> world poses ``[B, T, 4, 4]`` or
        past displacements ``[B, T - 1, 2]``, :func:`split_past_motion`)."""
        poses, actions = split_past_motion(motion)
        return Past(occupancy, poses, actions, self.planes(occupancy, poses))
