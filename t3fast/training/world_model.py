"""Stage 2: training the forecaster and planner, fine-tuning the decoder (a
:class:`~t3fast.training.trainer.Task`).

The encoder of a stage-1 checkpoint is frozen. Each training sample is an 11-frame window;
a rollout of ``loss.rollout_steps`` autoregressive steps starts at a random future step
``k``. Its history is what the model would have at step ``k`` at inference: the encoded
frames up to the present and the model's own predictions of steps ``0 .. k-1``, computed
without gradients (the "pushforward" trick of Brandstetter et al. 2022: training sees its
own errors, at the cost of forward passes only); later steps of the rollout see the
model's predictions with gradients. The loss of each predicted step is

    L1(next, enc(frame)) + gamma * MSE(next, enc(frame))        # triplane
    + xi * (CE + Lovasz)(decoder(next) at sampled points)      # occupancy
    + action_weight * |a - a_true|^2                            # planning

averaged over the rollout's steps. ``rollout_steps = 6`` trains the full 3 s rollout every
step; the CPU presets use shorter rollouts from random starts (the same per-step queries
and targets, a fraction of the cost).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from torch import Tensor, nn
from torch.nn import functional as F
from torch.utils.data import Dataset

from t3fast.data.classes import FREE, IGNORE
from t3fast.data.sample import NUM_FUTURE, PRESENT, DrivingSample
from t3fast.data.synthetic import SyntheticDriving
from t3fast.io.checkpoint import AUTOENCODER, read_checkpoint
from t3fast.io.config import config_to_dict, load_config
from t3fast.models.config import AutoencoderConfig
from t3fast.models.ego_motion import planar_poses, warp_sequence
from t3fast.models.triplane import Triplane
from t3fast.models.world_model import T3Former
from t3fast.training.configs import Stage2Config, WorldLossConfig
from t3fast.training.losses import occupancy_loss
from t3fast.training.sampling import sample_changed_points, sample_query_points
from t3fast.training.triplane_cache import cached_scene_triplanes


@dataclass
class SequenceBatch:
    """Training windows: ``occ`` uint8 ``[B, 11, X, Y, Z]``; ``planes`` the frames' encoded
    triplanes ``[B, 11, C, H, W]`` (None: encode ``occ`` in the step); actions ``[B, 4, 2]``
    and ``[B, 6, 2]`` (present frame); the frames' poses."""

    occ: Tensor
    planes: Triplane | None
    past_actions: Tensor
    future_actions: Tensor
    ego_poses: Tensor  # ``[B, 11, 4, 4]`` ego -> world

    def to(self, device: torch.device | str) -> SequenceBatch:
        planes = None if self.planes is None else self.planes.map(lambda p: p.to(device))
        moved = {f.name: getattr(self, f.name).to(device) for f in fields(self) if f.name != "planes"}
        return SequenceBatch(planes=planes, **moved)


class EncodedWindows(Dataset):
    """Synthetic windows with their frames' triplanes from a per-scene cache."""

    def __init__(self, windows: SyntheticDriving, planes: list[Triplane]):
        self.windows, self.planes = windows, planes

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> tuple[DrivingSample, Triplane]:
        sample = self.windows[index]
        scene = index // len(self.windows.starts)
        window = slice(sample.start, sample.start + sample.occ.shape[0])
        return sample, self.planes[scene].map(lambda p: p[window].float())


def collate_windows(items: list) -> SequenceBatch:
    """Items are ``DrivingSample``s or ``(DrivingSample, Triplane)`` pairs."""
    pairs = [item if isinstance(item, tuple) else (item, None) for item in items]
    samples = [s for s, _ in pairs]
    planes = None
    if pairs[0][1] is not None:
        per_plane = zip(*(t for _, t in pairs))
        planes = Triplane(*(None if first is None else torch.stack(ps) for first, ps in zip(pairs[0][1], per_plane)))
    return SequenceBatch(
        occ=torch.stack([s.occ for s in samples]),
        planes=planes,
        past_actions=torch.stack([s.past_actions for s in samples]),
        future_actions=torch.stack([s.future_actions for s in samples]),
        ego_poses=torch.stack([s.ego_poses for s in samples]),
    )


@torch.no_grad()
def ego_aligned_window(
    model: T3Former, occ: Tensor, ego_poses: Tensor, frames: Sequence[int] | None = None
) -> tuple[Triplane, Tensor]:
    """The 11 frames of windows ``occ`` ``[B, 11, X, Y, Z]`` moved into the present ego frame
    (poses ``[B, 11, 4, 4]``): (their encoded planes ``[B, 11, C, H, W]``, the moved labels with
    ``IGNORE`` where a frame did not see that part of the present grid).

    The past frames are encoded as at inference (:meth:`T3Former.encode_history`: what a past
    frame did not see is free). A future frame's target keeps the present frame's content
    where that future frame did not look: the static world does not vanish behind the ego.
    ``frames``: encode only these (a rollout reads a few; encoding is half a step's cost), the
    planes of the others stay zero.
    """
    poses = planar_poses(ego_poses, PRESENT)
    moved = warp_sequence(occ, poses, fill=IGNORE)
    unseen = moved == IGNORE
    history = moved[:, : PRESENT + 1].masked_fill(unseen[:, : PRESENT + 1], FREE)
    future = torch.where(unseen[:, PRESENT + 1 :], occ[:, PRESENT : PRESENT + 1], moved[:, PRESENT + 1 :])
    inputs = torch.cat([history, future], dim=1)
    if frames is None:
        return model.encode_sequence(inputs), moved
    index = torch.tensor(sorted(set(frames)), device=occ.device)
    encoded = model.encode_sequence(inputs[:, index])

    def scatter(p: Tensor) -> Tensor:
        full = p.new_zeros(p.shape[0], occ.shape[1], *p.shape[2:])
        full[:, index] = p
        return full

    return encoded.map(scatter), moved


def rollout_frames(first: int, steps: int, pushforward: bool) -> list[int]:
    """Window frames a rollout of ``steps`` steps from future step ``first`` reads: the past
    and present, the encoded future frames it starts from (none with pushforward: its own
    predictions), and its targets."""
    start = PRESENT + 1 + (first if pushforward else 0)
    return list(range(PRESENT + 1)) + list(range(start, PRESENT + 1 + first + steps))


def load_autoencoder_into(model: T3Former, weights: dict[str, Tensor]) -> None:
    """Copy a stage-1 state dict's encoder and decoder weights into ``model``."""
    model.encoder.load_state_dict({k[len("encoder."):]: v for k, v in weights.items() if k.startswith("encoder.")})
    model.decoder.load_state_dict({k[len("decoder."):]: v for k, v in weights.items() if k.startswith("decoder.")})


def build_world_model(cfg: Stage2Config) -> T3Former:
    """The untrained world model of ``cfg`` (``cfg.autoencoder`` must be set)."""
    if cfg.autoencoder is None:
        raise ValueError("Stage2Config.autoencoder is unset: resolve it from the stage-1 checkpoint first")
    return T3Former.from_config(cfg.autoencoder, cfg.model)


def rollout_loss(
    model: nn.Module, planes: Triplane, occ: Tensor, past_actions: Tensor, future_actions: Tensor, first: int,
    steps: int, loss: WorldLossConfig,
) -> tuple[Tensor, dict[str, float]]:
    """Stage-2 loss of one rollout of ``steps`` steps starting at future step ``first``.

    With ``loss.pushforward`` the history of step ``first`` holds the model's own predictions of
    the ``first`` earlier future steps and the planner continues from its own plan of them (both
    computed without gradients), as at inference, instead of encoded ground truth and true
    displacements: the planner is trained on its own rollouts, its errors included.

    Args:
        planes: encoded frames ``[B, 11, C, H, W]``; occ: labels ``[B, 11, X, Y, Z]``.
    """
    history = planes.map(lambda p: p[:, : PRESENT + 1 + first])  # the forecaster reads the last 5
    actions = torch.cat([past_actions, future_actions[:, :first]], dim=1)
    if loss.pushforward and first:
        core = model.module if hasattr(model, "module") else model
        history = planes.map(lambda p: p[:, : PRESENT + 1])
        with torch.no_grad():
            frames, _, planned = core.rollout(history, past_actions, first)
        for frame in frames:
            history = history.append(frame)
        actions = torch.cat([past_actions, planned], dim=1)
    targets = [PRESENT + 1 + first + j for j in range(steps)]
    slots = (loss.num_occupied, loss.num_near_free, loss.num_far_free)
    queries = [sample_query_points(occ[:, t], *slots) for t in targets]
    if loss.num_changed:
        changed = [sample_changed_points(occ[:, t], occ[:, PRESENT], loss.num_changed) for t in targets]
        queries = [tuple(torch.cat(pair, dim=1) for pair in zip(q, c)) for q, c in zip(queries, changed)]
    futures, predicted, logits = model(history, actions, steps, first, [q[0] for q in queries])
    tri = occ_loss = torch.zeros((), device=occ.device)
    for j, t in enumerate(targets):
        for p, target in zip(futures[j], planes):
            if p is not None:
                tri = tri + F.l1_loss(p, target[:, t]) + loss.gamma * F.mse_loss(p, target[:, t])
        occ_loss = occ_loss + occupancy_loss(logits[j], queries[j][1], lovasz_weight=loss.lovasz_weight)[0]
    act = (predicted - future_actions[:, first : first + steps]).square().sum(-1).mean()
    tri, occ_loss = tri / steps, occ_loss / steps
    total = tri + loss.xi * occ_loss + loss.action_weight * act
    parts = {"triplane": tri, "occupancy": occ_loss, "action": act}
    return total, {k: float(v.detach()) for k, v in parts.items()}


class WorldModelTask:
    """Trains :class:`T3Former` (stage 2); scores the Avg mIoU of full rollouts on val windows."""

    def __init__(self, cfg: Stage2Config):
        self.cfg = copy.deepcopy(cfg)
        self._stage1 = read_checkpoint(self.cfg.autoencoder_ckpt, AUTOENCODER)  # read once: config and weights
        if self.cfg.autoencoder is None:
            self.cfg.autoencoder = load_config(AutoencoderConfig, self._stage1["config"]["task"]["model"])
        self._val = None
        self._encoder = None

    def build_model(self) -> nn.Module:
        model = build_world_model(self.cfg)
        load_autoencoder_into(model, self._stage1["model"])
        if self.cfg.decoder_lr_scale == 0:
            model.decoder.requires_grad_(False)  # still passes the occupancy loss on to the forecaster
        if self.cfg.planner_lr_scale == 0:
            model.planner.requires_grad_(False)
        self._encoder = model.encoder
        return model

    def train_dataset(self) -> Dataset:
        data = self.cfg.data
        if data.source == "synthetic":
            windows = SyntheticDriving("train", data.train_scenes, data.frames_per_scene, stride=data.stride)
            if self.cfg.model.ego_aligned:  # moved into each window's present frame, encoded in the step
                return windows
            if self._encoder is None:
                raise RuntimeError("build_model() must run before train_dataset()")
            planes = cached_scene_triplanes(self._encoder, windows.scenes, data.cache_dir)
            return EncodedWindows(windows, planes)
        if data.source == "occ3d":
            from t3fast.data.occ3d import Occ3DNuScenes

            return Occ3DNuScenes(data.occ3d_root, data.occ3d_train_info, stride=data.stride)
        raise ValueError(f"data.source must be 'synthetic' or 'occ3d', got {data.source!r}")

    def collate(self, batch_list: list) -> SequenceBatch:
        return collate_windows(batch_list)

    def samples_in(self, batch: SequenceBatch) -> int:
        return batch.occ.shape[0]

    def training_step(self, model: nn.Module, batch: SequenceBatch) -> tuple[Tensor, dict[str, float]]:
        core = model.module if hasattr(model, "module") else model
        steps = self.cfg.loss.rollout_steps
        if not 1 <= steps <= NUM_FUTURE:
            raise ValueError(f"loss.rollout_steps must be in [1, {NUM_FUTURE}], got {steps}")
        first = int(torch.randint(0, NUM_FUTURE - steps + 1, ()))
        occ = batch.occ
        if core.ego_aligned:
            frames = rollout_frames(first, steps, self.cfg.loss.pushforward)
            planes, occ = ego_aligned_window(core, batch.occ, batch.ego_poses, frames)
        else:
            planes = batch.planes if batch.planes is not None else core.encode_sequence(batch.occ)
        return rollout_loss(model, planes, occ, batch.past_actions, batch.future_actions, first, steps, self.cfg.loss)

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        """Avg mIoU (absent classes skipped), IoU and planning L2 of full rollouts on the val
        windows; the first call also logs Copy&Paste and the constant-velocity warp on the same
        windows, so every later score can be read against them."""
        from t3fast.evaluation.world_model import (
            copy_paste_method,
            evaluate_many,
            t3former_method,
            warp_const_vel_method,
        )

        data = self.cfg.data
        device = next(model.parameters()).device
        first = self._val is None
        if first:
            self._val = SyntheticDriving("val", data.val_scenes, data.frames_per_scene, stride=data.val_stride)
        indices = list(range(min(len(self._val), data.val_windows)))
        methods = {"t3former": t3former_method(model)}
        if first:  # the baselines once, in the same pass over the windows
            methods.update(copy_paste=copy_paste_method, warp_const_vel=warp_const_vel_method)
        records = evaluate_many(methods, self._val, indices, device=device, progress=False, absent="skip")
        result = records.pop("t3former")
        values = {"score": result["miou"]["avg"], "miou_avg": result["miou"]["avg"], "iou_avg": result["iou"]["avg"],
                  "miou_0s": result["miou"]["0s"], "l2_mean_avg": result["l2_mean"]["avg"]}
        for name, base in records.items():
            values.update({f"{name}_miou_avg": base["miou"]["avg"], f"{name}_iou_avg": base["iou"]["avg"]})
        return values

    def lr_scales(self) -> dict[str, float]:
        # at the full rate, the occupancy loss of early, poor forecasts overwrites the decoder
        # (reconstruction fell from 92 to 43 mIoU within 200 steps)
        scales = {"decoder": self.cfg.decoder_lr_scale, "planner": self.cfg.planner_lr_scale}
        return {name: scale for name, scale in scales.items() if scale and scale != 1.0}

    def config_dict(self) -> dict:
        return config_to_dict(self.cfg)

