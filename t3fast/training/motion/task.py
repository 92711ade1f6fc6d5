"""The motion head's own :class:`~t3fast.training.task.Task`: a trained world model whose flow
forecaster's motion head (the learned correction of the tracker's agent velocities) is trained
anew on many cached windows (:mod:`t3fast.training.motion.motion_cache`), everything else frozen.

Trained alongside the forecaster on its 30 scenes, the head fitted them: its agents moved 3.46
cells off on training windows against the tracker's 3.56, and on validation 3.80 against 3.94,
too little to show in the forecast. Like the route planner (:mod:`t3fast.training.planner`), it
reads only the tracker's velocities and two encoded planes a window, so it can learn from ten
times the scenes at the same cost. The loss is the flow term of the world model's loss
(:func:`~t3fast.training.world_model.motion_loss.flow_terms`): per agent and step, the L1
between the displacement the render moves it by and its true motion, the moving agents and the
parked ones averaged apart, plus ``precision_weight`` x the moving agents' mean miss
``1 - exp(-d^2 / 2 s^2)`` (0 at an exact motion, 1 far off: what an agent's IoU does).
``best.pt`` follows the agents' error on the validation windows
(moving and parked, weighted as in the loss); each evaluation also scores the tracker (the head
at zero) on the same windows, and the share of moving agents drawn within a cell (``*_within_1``).
Checkpoints are whole world models: ``t3fast eval`` and ``t3fast export`` take them as they are.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from t3fast.data.synthetic import SyntheticDriving
from t3fast.device_constants import device_constant
from t3fast.errors import ConfigError
from t3fast.evaluation.planning import HORIZONS as STEPS_AT
from t3fast.io.checkpoint import WORLD_MODEL, read_checkpoint
from t3fast.models.flow_forecaster import tracker_motion
from t3fast.models.world_model import T3Former
from t3fast.pretrained import resolve, world_model_from_checkpoint
from t3fast.training.configs import MotionConfig
from t3fast.training.distributed import barrier, is_main
from t3fast.training.motion.motion_cache import MotionBatches, MotionCache, MotionWindows
from t3fast.training.step_draws import CoinToss
from t3fast.training.world_model.motion_loss import AgentTargets, agent_errors, flow_terms, masked_mean

VAL_CHUNK = 50  # validation windows per forward pass
HORIZONS = {name: steps - 1 for name, steps in STEPS_AT.items()}  # future step index of each horizon


def mirror_left_right(batch: MotionWindows) -> MotionWindows:
    """The windows mirrored across the ego's x axis: planes, velocities and the agents' cells
    flipped along y (the W axis), the y components of the velocities and motions negated."""
    sign = device_constant((1.0, -1.0, 1.0, -1.0), batch.velocity.dtype, batch.velocity.device).view(1, 4, 1, 1)
    t = batch.targets
    motion = t.motion * device_constant((1.0, -1.0), t.motion.dtype, t.motion.device)
    targets = AgentTargets(t.cells.flip(-1), t.visible, motion)
    return MotionWindows(batch.present.flip(-1), batch.previous.flip(-1), batch.velocity.flip(-1) * sign, targets)


def motion_head_loss(displacements: Tensor, targets: AgentTargets,
                     cfg: MotionConfig) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss of the module doc for the head's displacements ``[B, S, 2, H, W]`` and its parts."""
    error, is_moving, is_parked = agent_errors(displacements, targets, cfg.min_flow)
    moving, parked = masked_mean(error, is_moving), masked_mean(error, is_parked)
    miss = masked_mean(1 - torch.exp(-0.5 * (error / cfg.precision_scale).square()), is_moving)
    loss = moving + cfg.parked_weight * parked + cfg.precision_weight * miss
    return loss, {"flow_moving": moving.detach(), "flow_parked": parked.detach(), "miss": miss.detach()}


class MotionHeadTraining(T3Former):
    """The world model as the motion head's training sees it (and DDP wraps): its forward is
    the flow forecaster's tracked motion."""

    def forward(self, velocity: Tensor, present: Tensor, previous: Tensor) -> Tensor:
        """:meth:`~t3fast.models.flow_forecaster.FlowTriplaneForecaster.tracked_motion` of the windows."""
        return self.forecaster.tracked_motion(velocity, present, previous)


class MotionTask:
    """Trains the motion head of ``cfg.world_model`` alone (see the module doc)."""

    def __init__(self, cfg: MotionConfig):
        self.cfg = copy.deepcopy(cfg)
        self._state = read_checkpoint(resolve(self.cfg.world_model), WORLD_MODEL)
        model_cfg = self._state["config"]["task"].get("model", {})
        if model_cfg.get("forecaster") != "flow":
            raise ConfigError(f"world_model {self.cfg.world_model!r} has no motion head to train: train-motion needs "
                              "model.forecaster = 'flow'")
        self._model: T3Former | None = None
        self._val: MotionWindows | None = None
        self._generator = torch.Generator().manual_seed(self.cfg.train.seed)
        self._mirror = CoinToss(self._generator)  # each step's batch mirrored left-right or not

    def build_model(self) -> nn.Module:
        """The world model with a new motion head (zero correction: the tracker); every other
        weight from ``cfg.world_model``."""
        model = world_model_from_checkpoint(self._state, self.cfg.world_model, MotionHeadTraining)
        model.forecaster.reset_motion_head()
        model.requires_grad_(False)
        model.forecaster.motion_head.requires_grad_(True)
        self._model = model
        return model

    def _cache(self, split: str, scenes: int) -> MotionCache:
        if self._model is None:
            raise RuntimeError("build_model() must run before the motion head's windows are read")
        data = self.cfg.data
        windows = SyntheticDriving(split, scenes, data.frames_per_scene, stride=data.stride)
        cache = MotionCache(windows, self._model, data.cache_dir)
        if is_main():
            cache.build()
        barrier()
        return cache

    def train_dataset(self) -> MotionBatches:
        """The training windows, held on the model's device where they fit."""
        return self._cache("train", self.cfg.data.train_scenes).batches(next(self._model.parameters()).device)

    def collate(self, batch: MotionWindows) -> MotionWindows:
        return batch  # gathered already collated (MotionBatches)

    def samples_in(self, batch: MotionWindows) -> int:
        return len(batch)

    def step_variant(self) -> bool:
        """Draws whether the next step mirrors its batch (``train.cuda_graph``: one graph each way)."""
        return self._mirror.draw()

    def training_step(self, model: nn.Module, batch: MotionWindows) -> tuple[Tensor, dict[str, Tensor]]:
        if self._mirror.take():
            batch = mirror_left_right(batch)
        displacements = model(batch.velocity, batch.present, batch.previous)
        loss, parts = motion_head_loss(displacements, batch.targets, self.cfg)
        with torch.no_grad():
            prior = flow_terms(tracker_motion(batch.velocity, displacements.shape[1]), batch.targets, self.cfg.min_flow)
        return loss, {**parts, "tracker_moving": prior[0], "tracker_parked": prior[1]}

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        """On every validation window, per agent and step, the error (plane cells, L1) of the
        head's displacements and of the tracker's: mean over the moving agents at 1, 2, 3 s and
        over all steps, and over the parked ones; ``ratio_*``: head / tracker; ``score`` is minus
        the loss's combination of the two (a parked car drawn drifting costs the forecast as much
        as a moving one drawn behind)."""
        if self._val is None:
            self._val = self._cache("val", self.cfg.data.val_scenes).all()
        device = next(model.parameters()).device
        sums: dict[str, Tensor] = {}
        for start in range(0, len(self._val), VAL_CHUNK):
            batch = self._val.select(slice(start, start + VAL_CHUNK)).to(device)
            learned = model.forecaster.tracked_motion(batch.velocity, batch.present, batch.previous)
            for name, displacements in (("head", learned), ("tracker", tracker_motion(batch.velocity,
                                                                                       learned.shape[1]))):
                error, is_moving, is_parked = agent_errors(displacements, batch.targets, self.cfg.min_flow)
                parts = {f"{name}_moving_{h}": (error[:, k], is_moving[:, k]) for h, k in HORIZONS.items()}
                parts.update({f"{name}_moving": (error, is_moving), f"{name}_parked": (error, is_parked),
                              f"{name}_within_1": ((error < 1).to(error.dtype), is_moving)})
                for key, (err, mask) in parts.items():
                    total = torch.stack([(err * mask).sum().double().cpu(), mask.sum().double().cpu()])
                    sums[key] = sums.get(key, torch.zeros(2, dtype=torch.float64)) + total
        values = {key: float(s[0] / s[1].clamp(min=1)) for key, s in sums.items()}
        for key in [k for k in values if k.startswith("head_")]:
            values[key.replace("head_", "ratio_")] = values[key] / max(values[key.replace("head_", "tracker_")], 1e-9)
        values["score"] = -(values["head_moving"] + self.cfg.parked_weight * values["head_parked"])
        return values

    def config_dict(self) -> dict:
        """The world model's own config (the checkpoints are world-model checkpoints)."""
        return copy.deepcopy(self._state["config"]["task"])

