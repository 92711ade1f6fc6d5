"""The settings of both training stages and of the loop, as plain dataclasses.

They load from YAML/JSON with dotted overrides (:func:`t3fast.io.config.load_config`); the
named ones are in :mod:`t3fast.presets`. A checkpoint stores its stage's config, so a run
can be resumed, evaluated or read back without its preset.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from t3fast.errors import ConfigError
from t3fast.models.config import AutoencoderConfig, WorldModelConfig


@dataclass
class TrainConfig:
    """Settings of :class:`Trainer` (load with :func:`t3fast.io.config.load_config`)."""

    steps: int = 1000  # optimiser steps in total
    batch_size: int = 8  # per process; the global batch is batch_size * world size
    lr: float = 1e-3  # peak learning rate
    min_lr: float = 1e-6  # reached by the cosine at the last step
    warmup_steps: int = 100  # linear warm-up (capped at steps)
    weight_decay: float = 0.01  # AdamW; not applied to biases, norm weights, embeddings
    grad_clip: float | None = 1.0  # max gradient norm; None disables clipping
    amp: bool = True  # CUDA only: bf16 autocast when supported, else fp16 with a GradScaler
    seed: int = 0
    log_every: int = 50  # steps between train log events
    eval_every: int = 1000  # steps between evaluations (also at the end); 0 never evaluates
    eval_at_start: bool = False  # also score the untrained model (step 0): the run's own baseline
    ckpt_every: int = 1000  # steps between last.pt writes (also at the end); 0: only at the end
    num_workers: int = 0  # DataLoader worker processes
    out_dir: str = "runs/train"
    tensorboard: bool = True  # used only if torch.utils.tensorboard imports
    resume: bool = False  # continue from out_dir/last.pt (must exist)
    resume_from: str | None = None  # continue from this checkpoint (must exist)
    overwrite: bool = False  # replace the run already in out_dir (a new run needs an empty out_dir)
    device: str = "auto"  # "auto" (CUDA when available), "cuda" or "cpu"

    def __post_init__(self) -> None:
        """Reject counts that would crash or silently do nothing later (e.g. a zero batch)."""
        at_least = {"steps": 1, "batch_size": 1, "warmup_steps": 0, "log_every": 0, "eval_every": 0,
                    "ckpt_every": 0, "num_workers": 0}
        for key, low in at_least.items():
            if getattr(self, key) < low:
                raise ConfigError(f"train.{key} must be at least {low}, got {getattr(self, key)}")


@dataclass
class FramesConfig:
    """Where single occupancy frames come from."""

    source: str = "synthetic"  # "synthetic" or "occ3d"
    train_scenes: int = 200  # synthetic scenes of the train split
    val_scenes: int = 2  # synthetic scenes scored during training
    val_stride: int = 4  # every k-th frame of those
    frames_per_scene: int = 40
    flip: bool = True  # random x/y flips of training frames
    occ3d_root: str = ""  # directory holding gts/
    occ3d_train_info: str = ""  # info pickles
    occ3d_val_info: str = ""


@dataclass
class LossConfig:
    """Stage-1 loss: cross-entropy + lovasz_weight * Lovasz-softmax."""

    lovasz_weight: float = 1.0
    class_weights: bool = False  # inverse-log-frequency CE weights, counted on the first frames
    class_weight_frames: int = 40  # training frames counted for those weights
    full_grid: bool = False  # decode every voxel instead of sampled points
    num_occupied: int = 40_000  # all occupied voxels up to this many per frame
    num_near_free: int = 20_000  # free voxels next to a surface
    num_far_free: int = 10_000  # other free voxels


@dataclass
class Stage1Config:
    """Everything ``t3fast train-ae`` needs."""

    model: AutoencoderConfig = field(default_factory=AutoencoderConfig)
    data: FramesConfig = field(default_factory=FramesConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    decoder_backend: str = "fused"  # "reference" for comparisons
    # a stage-1 or stage-2 checkpoint whose encoder and decoder weights training starts from
    # (fine-tuning: a new data layout, or synthetic -> Occ3D); "" starts from scratch
    init_from: str = ""


@dataclass
class SequencesConfig:
    """Where the 11-frame windows come from."""

    source: str = "synthetic"  # "synthetic" or "occ3d"
    train_scenes: int = 200
    val_scenes: int = 4  # scored during training (absent classes left out of mIoU)
    val_windows: int = 16  # at most this many windows of those scored
    val_stride: int = 8  # frames between the starts of scored windows
    frames_per_scene: int = 40
    stride: int = 1  # frames between consecutive training windows
    cache_dir: str = "runs/cache"  # encoded triplanes of the synthetic training scenes
    occ3d_root: str = ""
    occ3d_train_info: str = ""
    occ3d_val_info: str = ""


@dataclass
class WorldLossConfig:
    """Stage-2 loss weights and the rollout trained per step."""

    gamma: float = 1.0  # weight of the L2 triplane term next to L1
    xi: float = 0.1  # weight of the occupancy loss on decoded predictions
    action_weight: float = 1.0
    lovasz_weight: float = 1.0
    rollout_steps: int = 6  # autoregressive steps per sample (1..6), from a random start
    pushforward: bool = True  # a rollout from step k > 0 starts from the model's own k predictions
    num_occupied: int = 10_000  # query points per predicted frame
    num_near_free: int = 5_000
    num_far_free: int = 2_000
    num_changed: int = 0  # more query points where the target differs from the present frame (what moved)


@dataclass
class Stage2Config:
    """Everything ``t3fast train-wm`` needs. ``autoencoder`` is filled from the stage-1
    checkpoint, so a stage-2 checkpoint describes its whole model."""

    autoencoder_ckpt: str = "runs/ae-small/best.pt"
    autoencoder: AutoencoderConfig | None = None
    decoder_lr_scale: float = 0.1  # the pretrained decoder is fine-tuned at this fraction of train.lr; 0 freezes it
    planner_lr_scale: float = 1.0  # the planner's fraction of train.lr; 0 freezes it
    model: WorldModelConfig = field(default_factory=WorldModelConfig)
    data: SequencesConfig = field(default_factory=SequencesConfig)
    loss: WorldLossConfig = field(default_factory=WorldLossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
