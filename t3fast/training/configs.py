"""The settings of both training stages and of the loop, as plain dataclasses.

They load from YAML/JSON with dotted overrides (:func:`t3fast.io.config.load_config`); the
named ones are in :mod:`t3fast.presets`. A checkpoint stores its stage's config, so a run
can be resumed, evaluated or read back without its preset.

Each one refuses, when it is built, values that would crash a run late or quietly ruin it
(a negative loss weight or gradient clip, a learning rate of zero): the :class:`ConfigError`
names the dotted key and the value.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from t3fast.data.sample import NUM_FUTURE
from t3fast.device import check_device_name
from t3fast.errors import ConfigError
from t3fast.models.config import AutoencoderConfig, WorldModelConfig


def _at_least(section: str, cfg: object, lows: Mapping[str, int]) -> None:
    """Counts: ``cfg.<key> >= low`` for each key."""
    for key, low in lows.items():
        value = getattr(cfg, key)
        if value < low:
            raise ConfigError(f"{section}{key} must be at least {low}, got {value}")


def _weights(section: str, cfg: object, keys: tuple[str, ...], zero: str) -> None:
    """Loss weights and learning-rate factors: finite and ``>= 0`` (a negative one ascends)."""
    for key in keys:
        value = getattr(cfg, key)
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{section}{key} must be >= 0 ({zero}), got {value}")


def _share(section: str, cfg: object, key: str) -> None:
    """A probability: ``cfg.<key>`` a number in ``[0, 1]``."""
    value = getattr(cfg, key)
    if not (isinstance(value, int | float) and 0 <= value <= 1):
        raise ConfigError(f"{section}{key} must be a share in [0, 1], got {value!r}")


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
    seed: int = 0  # in [0, 2**63)
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
    profile_steps: int = 0  # profile this many steps (after two) into out_dir/profile.json; 0: none
    # each step replayed as one CUDA graph (t3fast.training.graphed_step): the task must name its
    # steps' host-side choices; off with several processes or float16 AMP
    cuda_graph: bool = False

    def __post_init__(self) -> None:
        """Reject counts and rates that would crash, do nothing or train backwards (e.g. a zero
        batch, a negative gradient clip, a final learning rate above the peak)."""
        _at_least("train.", self, {"steps": 1, "batch_size": 1, "warmup_steps": 0, "log_every": 0,
                                   "eval_every": 0, "ckpt_every": 0, "num_workers": 0, "profile_steps": 0})
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ConfigError(f"train.lr must be a number > 0, got {self.lr}")
        if not (math.isfinite(self.min_lr) and 0 <= self.min_lr <= self.lr):
            raise ConfigError(f"train.min_lr must be between 0 and train.lr ({self.lr}), got {self.min_lr}")
        _weights("train.", self, ("weight_decay",), "0 turns it off")
        if self.grad_clip is not None and not self.grad_clip >= 0:  # also NaN
            raise ConfigError(f"train.grad_clip must be >= 0 (0 disables clipping), got {self.grad_clip}")
        if not 0 <= self.seed < 2**63:  # what every generator seeded from it takes
            raise ConfigError(f"train.seed must be an integer in [0, 2**63), got {self.seed}")
        check_device_name(self.device, "train.device")


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

    def __post_init__(self) -> None:
        _at_least("data.", self, {"val_stride": 1})


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

    def __post_init__(self) -> None:
        _weights("loss.", self, ("lovasz_weight",), "0 turns the term off")
        _at_least("loss.", self, {"class_weight_frames": 1, "num_occupied": 0, "num_near_free": 0, "num_far_free": 0})


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
    # ego-aligned models: train on windows encoded once in their present frame and kept in
    # cache_dir (built, with a progress bar, before the first step); the flow forecaster needs it
    latent_cache: bool = False
    latent_flips: bool = True  # each cached training batch randomly mirrored / transposed (8 ways)
    # with latent_cache, the Delta forecaster on the whole stage-2 loss (its decoded predictions'
    # occupancy term too): each window's labels come with its cached planes and are moved into
    # its present frame in the step; the encoder leaves the step, the loss stays the labels
    # path's (no latent_flips there)
    cache_labels: bool = False
    occ3d_root: str = ""
    occ3d_train_info: str = ""
    occ3d_val_info: str = ""

    def __post_init__(self) -> None:
        _at_least("data.", self, {"val_stride": 1, "stride": 1})


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
    # the flow forecaster on cached windows (t3fast.training.world_model.motion_loss)
    agent_weight: float = 20.0  # extra latent-loss weight of the cells an agent covers now or then
    flow_weight: float = 0.1  # weight of the flow term (L1 in plane cells on the agents' cells)
    static_flow_weight: float = 0.1  # within the flow term: the flow's size where nothing moves
    # the route planner (model.planner=route): share of training windows planned without the command
    command_dropout: float = 0.3

    def __post_init__(self) -> None:
        _weights("loss.", self, ("gamma", "xi", "action_weight", "lovasz_weight", "agent_weight", "flow_weight",
                                 "static_flow_weight"), "0 turns the term off")
        if not 1 <= self.rollout_steps <= NUM_FUTURE:
            raise ConfigError(f"loss.rollout_steps must be in [1, {NUM_FUTURE}], got {self.rollout_steps}")
        _share("loss.", self, "command_dropout")
        _at_least("loss.", self, {"num_occupied": 0, "num_near_free": 0, "num_far_free": 0, "num_changed": 0})


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

    def __post_init__(self) -> None:
        _weights("", self, ("decoder_lr_scale", "planner_lr_scale"), "0 freezes that part")


@dataclass
class PlanDataConfig:
    """The windows a part trained on its own (the route planner, the motion head) trains and is
    selected on (synthetic; cached)."""

    train_scenes: int = 300
    val_scenes: int = 40  # the part is selected on these
    stride: int = 2  # frames between consecutive windows, in both splits
    frames_per_scene: int = 40
    cache_dir: str = "runs/cache"

    def __post_init__(self) -> None:
        _at_least("data.", self, {"train_scenes": 1, "val_scenes": 1, "stride": 1})


@dataclass
class PlannerConfig:
    """Everything ``t3fast train-planner`` needs: the route planner of a trained world model
    trained anew on its own, on many windows; the rest of the world model stays as it is."""

    world_model: str = "wm-small"  # shipped name or stage-2 checkpoint (model.planner must be "route")
    scene: bool = True  # the planner reads the road ahead (model.route_scene of the world model it goes into)
    modes: int = 1  # candidate plans (model.route_modes): winner-takes-all, scored by a cross-entropy
    command_dropout: float = 0.3  # share of training windows planned without the route command
    # + precision_weight x mean(1 - exp(-d^2 / 2 s^2)), s = precision_scale metres: a forecast
    # rendered from a pose is right only when the pose is within a voxel or two, so reward plans
    # that are nearly exact over plans that are less wrong on average
    precision_weight: float = 0.0
    precision_scale: float = 0.5
    data: PlanDataConfig = field(default_factory=PlanDataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        _share("", self, "command_dropout")
        _weights("", self, ("precision_weight",), "0 turns the term off")
        _at_least("", self, {"modes": 1})
        if not (math.isfinite(self.precision_scale) and self.precision_scale > 0):
            raise ConfigError(f"precision_scale must be > 0 metres, got {self.precision_scale}")


@dataclass
class BoxDataConfig:
    """The windows the box motion network trains and is selected on: synthetic train-split scenes,
    the last ``select_scenes`` of them held out to select it (the validation and test splits stay
    for scoring the forecast)."""

    train_scenes: int = 560
    select_scenes: int = 40
    stride: int = 4  # frames between consecutive windows
    frames_per_scene: int = 40
    cache_dir: str = "runs/cache"

    def __post_init__(self) -> None:
        _at_least("data.", self, {"train_scenes": 1, "select_scenes": 1, "stride": 1})


@dataclass
class BoxMotionConfig:
    """Everything ``t3fast train-box-motion`` needs: a box motion network
    (:mod:`t3fast.models.box_motion`) for a world model that draws fitted boxes, trained on its
    own; the rest of the world model stays as it is."""

    world_model: str = "wm-small"  # shipped name or stage-2 checkpoint (model.agent_boxes must be true)
    data: BoxDataConfig = field(default_factory=BoxDataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


@dataclass
class MotionConfig:
    """Everything ``t3fast train-motion`` needs: the motion head of a trained world model's flow
    forecaster trained anew on its own, on many windows; the rest stays as it is."""

    world_model: str = "wm-small"  # shipped name or stage-2 checkpoint (a flow forecaster)
    min_flow: float = 0.5  # plane cells an agent moves in a step to count as moving
    parked_weight: float = 1.0  # x the error of seen agents that did not move (a parked car must stand still)
    # + precision_weight x mean over moving agents of 1 - exp(-d^2 / 2 s^2), s = precision_scale
    # plane cells: an agent drawn more than its size off scores nothing, however far off it is
    precision_weight: float = 0.0
    precision_scale: float = 0.5
    data: PlanDataConfig = field(default_factory=PlanDataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def __post_init__(self) -> None:
        _weights("", self, ("parked_weight", "min_flow", "precision_weight"), "0 turns it off")
        if not (math.isfinite(self.precision_scale) and self.precision_scale > 0):
            raise ConfigError(f"precision_scale must be > 0 plane cells, got {self.precision_scale}")
