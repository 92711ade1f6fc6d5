"""The stage-2 :class:`~t3fast.training.task.Task`: builds the world model from a stage-1
checkpoint, feeds it windows, scores its rollouts on validation windows."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.utils.data import Dataset

from t3fast.data.sample import NUM_FUTURE
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import ConfigError
from t3fast.io.checkpoint import AUTOENCODER, WORLD_MODEL, checkpoint_kind, read_checkpoint
from t3fast.io.config import config_to_dict, load_config
from t3fast.models.config import AutoencoderConfig
from t3fast.models.world_model import T3Former
from t3fast.pretrained import resolve
from t3fast.training.configs import Stage2Config
from t3fast.training.distributed import barrier, is_main
from t3fast.training.gathered import fits_on
from t3fast.training.step_draws import toss
from t3fast.training.triplane_cache import cached_scene_triplanes
from t3fast.training.world_model.delta_loss import delta_rollout_loss
from t3fast.training.world_model.forwards import FlowMotionModel, RolloutModel
from t3fast.training.world_model.latent_cache import (
    AlignedBatch,
    AlignedBatches,
    AlignedLatentCache,
    AlignedWindow,
    LabelledAlignedWindows,
    ResidentAlignedWindows,
    collate_aligned,
    resident_bytes,
)
from t3fast.training.world_model.latent_flips import draw_flips, flip_aligned, random_flips
from t3fast.training.world_model.loss import rollout_loss
from t3fast.training.world_model.motion_loss import motion_loss
from t3fast.training.world_model.plan_loss import plan_batch
from t3fast.training.world_model.windows import (
    EncodedWindows,
    SequenceBatch,
    collate_windows,
    ego_aligned_window,
    moved_window,
    rollout_frames,
)


def load_autoencoder_into(model: T3Former, weights: dict[str, Tensor]) -> None:
    """Copy a stage-1 state dict's encoder and decoder weights into ``model``."""
    model.encoder.load_state_dict({k[len("encoder."):]: v for k, v in weights.items() if k.startswith("encoder.")})
    model.decoder.load_state_dict({k[len("decoder."):]: v for k, v in weights.items() if k.startswith("decoder.")})


def build_world_model(cfg: Stage2Config) -> RolloutModel | FlowMotionModel:
    """The untrained world model of ``cfg`` (``cfg.autoencoder`` must be set), with the training
    forward of its forecaster."""
    if cfg.autoencoder is None:
        raise ValueError("Stage2Config.autoencoder is unset: resolve it from the stage-1 checkpoint first")
    training = FlowMotionModel if cfg.model.forecaster == "flow" else RolloutModel
    return training.from_config(cfg.autoencoder, cfg.model)


@dataclass(frozen=True)
class StepChoices:
    """The host-side random choices of a stage-2 step, each None where its path has none: the
    route planner's left-right mirror and the latent windows' flips (x, y, transpose) on the
    cached latent windows, and where the rollout starts."""

    plan_mirror: bool | None
    flips: tuple[bool, bool, bool] | None
    start: int | None


class WorldModelTask:
    """Trains :class:`T3Former` (stage 2); scores the Avg mIoU of full rollouts on val windows."""

    _drawn: StepChoices | None = None  # drawn by step_variant for the next step

    def __init__(self, cfg: Stage2Config):
        self.cfg = copy.deepcopy(cfg)
        # read once: config and weights; a world model's checkpoint (e.g. a shipped one) lends its
        # encoder and decoder, so stage 2 can start from a shipped model without its stage-1 run
        source = Path(self.cfg.autoencoder_ckpt)
        if len(source.parts) == 1 and not source.is_file():  # a bare name: a shipped model
            source = resolve(source)
        self._stage1 = read_checkpoint(source, (AUTOENCODER, WORLD_MODEL))
        if self.cfg.autoencoder is None:
            task = self._stage1["config"]["task"]
            source = task["model"] if checkpoint_kind(self._stage1) == AUTOENCODER else task["autoencoder"]
            self.cfg.autoencoder = load_config(AutoencoderConfig, source)
        if self.cfg.model.forecaster == "flow" and not (self.cfg.data.latent_cache and self.cfg.model.ego_aligned):
            raise ConfigError("model.forecaster=flow trains on cached ego-aligned windows: set data.latent_cache=true "
                              "and model.ego_aligned=true")
        if self.cfg.data.cache_labels and not (self.cfg.data.latent_cache and self.cfg.model.ego_aligned
                                               and self.cfg.model.forecaster != "flow"):
            raise ConfigError("data.cache_labels reads the labels beside the planes of cached ego-aligned windows for "
                              "the Delta forecaster: set data.latent_cache=true and model.ego_aligned=true (the flow "
                              "forecaster trains on its own loss)")
        self._val = None
        self._encoder = self._model = None

    def build_model(self) -> nn.Module:
        model = build_world_model(self.cfg)
        load_autoencoder_into(model, self._stage1["model"])
        if self.cfg.decoder_lr_scale == 0:
            model.decoder.requires_grad_(False)  # still passes the occupancy loss on to the forecaster
        if self.cfg.planner_lr_scale == 0:
            model.planner.requires_grad_(False)
        self._encoder, self._model = model.encoder, model
        return model

    def train_dataset(self) -> Dataset:
        data = self.cfg.data
        if data.source == "synthetic":
            windows = SyntheticDriving("train", data.train_scenes, data.frames_per_scene, stride=data.stride)
            if self._encoder is None and (data.latent_cache or not self.cfg.model.ego_aligned):
                raise RuntimeError("build_model() must run before train_dataset()")
            if self.cfg.model.ego_aligned and data.latent_cache:  # moved and encoded once, read from disk
                cache = AlignedLatentCache(windows, self._model, data.cache_dir)
                if is_main():
                    cache.build()
                barrier()
                device = next(self._model.parameters()).device  # the windows are held there if they fit
                if not data.cache_labels:  # else read from disk by the loader
                    fits = fits_on(device, cache.stored_bytes())
                    return AlignedBatches(cache, device, progress=is_main()) if fits else cache
                labelled = LabelledAlignedWindows(cache)
                fits = fits_on(device, resident_bytes(labelled))
                return ResidentAlignedWindows(labelled, device, progress=is_main()) if fits else labelled
            if self.cfg.model.ego_aligned:  # moved into each window's present frame, encoded in the step
                return windows
            planes = cached_scene_triplanes(self._encoder, windows.scenes, data.cache_dir)
            return EncodedWindows(windows, planes)
        if data.source == "occ3d":
            from t3fast.data.occ3d import Occ3DNuScenes

            return Occ3DNuScenes(data.occ3d_root, data.occ3d_train_info, stride=data.stride)
        raise ValueError(f"data.source must be 'synthetic' or 'occ3d', got {data.source!r}")

    def collate(self, batch_list: list | SequenceBatch | AlignedBatch) -> SequenceBatch | AlignedBatch:
        if isinstance(batch_list, (SequenceBatch, AlignedBatch)):  # gathered whole, already collated
            return batch_list
        if isinstance(batch_list[0], AlignedWindow):
            return collate_aligned(batch_list)
        return collate_windows(batch_list)

    def samples_in(self, batch: SequenceBatch | AlignedBatch) -> int:
        return batch.planes.xy.shape[0] if isinstance(batch, AlignedBatch) else batch.occ.shape[0]

    def training_step(self, model: nn.Module, batch: SequenceBatch | AlignedBatch) -> tuple[Tensor, dict[str, Tensor]]:
        core = model.module if hasattr(model, "module") else model
        drawn, self._drawn = self._drawn, None  # without a variant drawn, the step draws its own choices
        if isinstance(batch, AlignedBatch):
            # a route planner that trains learns on the same windows, mirrored left-right only
            mirror = None if drawn is None else drawn.plan_mirror
            dropout = self.cfg.loss.command_dropout
            plan = plan_batch(batch, dropout, mirror=mirror) if self._trains_planner(core) else None
            if not self.cfg.data.latent_flips:
                flipped = batch
            else:
                flipped = random_flips(batch) if drawn is None else flip_aligned(batch, *drawn.flips)
            if self.cfg.model.forecaster != "flow":
                start = self._rollout_start() if drawn is None else drawn.start
                return delta_rollout_loss(model, flipped, self.cfg.loss, start)
            return motion_loss(model, flipped, self.cfg.loss, plan=plan)
        steps = self.cfg.loss.rollout_steps
        first = self._rollout_start() if drawn is None else drawn.start
        occ = batch.occ
        if core.ego_aligned and batch.planes is not None:  # encoded once (the encoder is frozen): read
            planes, occ = batch.planes, moved_window(batch.occ, batch.ego_poses)
        elif core.ego_aligned:
            frames = rollout_frames(first, steps, self.cfg.loss.pushforward)
            planes, occ = ego_aligned_window(core, batch.occ, batch.ego_poses, frames)
        else:
            planes = batch.planes if batch.planes is not None else core.encode_sequence(batch.occ)
        return rollout_loss(model, planes, occ, batch.past_actions, batch.future_actions, first, steps, self.cfg.loss)

    def step_variant(self) -> StepChoices:
        """Draws the next step's host-side choices, which that step uses (``train.cuda_graph``
        replays one graph per variant; see :class:`~t3fast.training.task.Task`): on the cached
        latent windows the planner's mirror and the flips, then the rollout start."""
        aligned = self.cfg.model.ego_aligned and self.cfg.data.latent_cache and not self.cfg.data.cache_labels
        mirror = toss() if aligned and self._trains_planner(self._model) else None
        flips = draw_flips() if aligned and self.cfg.data.latent_flips else None
        start = self._rollout_start() if self.cfg.model.forecaster != "flow" else None
        self._drawn = StepChoices(mirror, flips, start)
        return self._drawn

    def _trains_planner(self, model: nn.Module | None) -> bool:
        """Whether a step of ``model`` on the cached latent windows also trains its route planner."""
        return model is not None and model.reads_command and self.cfg.planner_lr_scale > 0

    def _rollout_start(self) -> int:
        """A random future step for a rollout of ``loss.rollout_steps`` steps to start at."""
        steps = self.cfg.loss.rollout_steps
        if not 1 <= steps <= NUM_FUTURE:
            raise ValueError(f"loss.rollout_steps must be in [1, {NUM_FUTURE}], got {steps}")
        return int(torch.randint(0, NUM_FUTURE - steps + 1, (), device="cpu"))

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        """Avg mIoU (absent classes skipped), IoU and planning L2 of full rollouts on the val
        windows; the first call also logs Copy&Paste and the constant-velocity warp on the same
        windows, so every later score can be read against them."""
        from t3fast.evaluation.world_model import (
            SharedRollout,
            copy_paste_method,
            evaluate_many,
            t3former_method,
            track_const_vel_method,
            track_gt_ego_method,
            warp_const_vel_method,
            warp_gt_ego_method,
        )

        data = self.cfg.data
        device = next(model.parameters()).device
        first = self._val is None
        if first:
            self._val = SyntheticDriving("val", data.val_scenes, data.frames_per_scene, stride=data.val_stride)
        indices = list(range(min(len(self._val), data.val_windows)))
        shared = SharedRollout(model)
        methods = {"t3former": t3former_method(model, shared=shared)}
        if model.ego_aligned:  # the forecast along the true poses: what the forecaster itself is worth
            methods["t3former_gt_ego"] = t3former_method(model, gt_ego=True, shared=shared)
        if first:  # the baselines once, in the same pass over the windows
            methods.update(copy_paste=copy_paste_method, warp_const_vel=warp_const_vel_method,
                           track_const_vel=track_const_vel_method, warp_gt_ego=warp_gt_ego_method,
                           track_gt_ego=track_gt_ego_method)
        records = evaluate_many(methods, self._val, indices, device=device, progress=False, absent="skip")
        result = records.pop("t3former")
        values = {"score": result["miou"]["avg"], "miou_avg": result["miou"]["avg"], "iou_avg": result["iou"]["avg"],
                  "miou_moving_avg": result["miou_moving"]["avg"], "miou_0s": result["miou"]["0s"],
                  "l2_mean_avg": result["l2_mean"]["avg"]}
        steered = records.pop("t3former_gt_ego", None)
        if steered is not None:
            # the planner is not what stage 2 trains here: best.pt follows the forecast at both the
            # planned and the true poses
            values["score"] = (result["miou"]["avg"] + steered["miou"]["avg"]) / 2
            values.update(gt_ego_miou_avg=steered["miou"]["avg"], gt_ego_miou_moving_avg=steered["miou_moving"]["avg"])
        for name, base in records.items():
            values.update({f"{name}_miou_avg": base["miou"]["avg"], f"{name}_iou_avg": base["iou"]["avg"],
                           f"{name}_miou_moving_avg": base["miou_moving"]["avg"]})
        return values

    def lr_scales(self) -> dict[str, float]:
        # at the full rate, the occupancy loss of early, poor forecasts overwrites the decoder
        # (reconstruction fell from 92 to 43 mIoU within 200 steps)
        scales = {"decoder": self.cfg.decoder_lr_scale, "planner": self.cfg.planner_lr_scale}
        return {name: scale for name, scale in scales.items() if scale and scale != 1.0}

    def config_dict(self) -> dict:
        return config_to_dict(self.cfg)

