"""The route planner's own :class:`~t3fast.training.task.Task`: a trained world model whose
route planner is trained anew on many cached windows (:mod:`t3fast.training.planner.plan_cache`)
while everything else stays frozen.

Trained alongside the forecaster, on its 30 scenes, the planner overfit them: its plans got
worse on validation within 250 steps. Here it reads 10x the scenes for the cost of two
encodings a window. Its checkpoints are the whole world model's (the frozen parts included),
so ``t3fast eval`` and ``t3fast export`` take them as they take a ``train-wm`` checkpoint;
``best.pt`` follows the planned positions' mean error on the validation windows, with and
without the route command (see :meth:`PlannerTask.evaluate`).
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from t3fast.data.route import mirror_command
from t3fast.data.synthetic import SyntheticDriving
from t3fast.device_constants import device_constant
from t3fast.errors import ConfigError
from t3fast.evaluation.planning import l2_summary
from t3fast.io.checkpoint import WORLD_MODEL, read_checkpoint
from t3fast.io.config import load_config
from t3fast.models.config import AutoencoderConfig, WorldModelConfig
from t3fast.models.planner import constant_turn_rate
from t3fast.models.route_planner import RoutePlanner
from t3fast.models.world_model import T3Former
from t3fast.pretrained import resolve, world_model_from_checkpoint
from t3fast.training.configs import PlannerConfig
from t3fast.training.distributed import barrier, is_main
from t3fast.training.planner.plan_cache import PlanBatches, PlanCache, PlanWindows
from t3fast.training.step_draws import CoinToss
from t3fast.training.world_model.plan_loss import drop_commands, plan_error


def mirror_left_right(batch: PlanWindows) -> PlanWindows:
    """The windows mirrored across the ego's x axis: planes flipped along y, y displacements
    negated, left and right turns swapped (the command follows the mirrored future)."""
    def flip_y(actions: Tensor) -> Tensor:
        return actions * device_constant((1.0, -1.0), actions.dtype, actions.device)

    return PlanWindows(batch.present.flip(-1), batch.previous.flip(-1), flip_y(batch.past_actions),
                       flip_y(batch.future_actions), mirror_command(batch.command))


class PlannerTraining(T3Former):
    """The world model as the planner's training sees it (and DDP wraps): its forward is the
    route planner's."""

    def forward(self, present: Tensor, previous: Tensor, past_actions: Tensor,
                command: Tensor | None) -> tuple[Tensor, Tensor]:
        """:meth:`~t3fast.models.route_planner.RoutePlanner.candidates` of the windows."""
        return self.planner.candidates(present, previous, past_actions, command)


def plan_summary(errors: Tensor) -> dict[str, float]:
    """L2 at 3 s and mean-L2 (mean over the steps up to 1, 2, 3 s, averaged; as
    :class:`~t3fast.evaluation.planning.PlanningMetrics`) of position errors ``[N, S]``."""
    l2 = l2_summary(errors)
    return {"l2_3s": l2["l2_at"]["3s"], "l2_mean": l2["l2_mean"]["avg"]}


class PlannerTask:
    """Trains the route planner of ``cfg.world_model`` alone (see the module doc)."""

    def __init__(self, cfg: PlannerConfig):
        self.cfg = copy.deepcopy(cfg)
        self._state = read_checkpoint(resolve(self.cfg.world_model), WORLD_MODEL)
        planner = self._state["config"]["task"].get("model", {}).get("planner")
        if planner != "route":
            raise ConfigError(f"world_model {self.cfg.world_model!r} has planner {planner!r}; train-planner trains a "
                              "route planner (model.planner = 'route')")
        self._model: T3Former | None = None
        self._val: PlanWindows | None = None
        self._generator = torch.Generator().manual_seed(self.cfg.train.seed)
        self._mirror = CoinToss(self._generator)  # each step's batch mirrored left-right or not

    def build_model(self) -> nn.Module:
        """The world model with a new route planner (constant turn rate: its last layer is zero)
        of ``cfg.scene``; every other weight from ``cfg.world_model``."""
        task = self.config_dict()
        fresh = RoutePlanner.from_config(load_config(AutoencoderConfig, task["autoencoder"]),
                                         load_config(WorldModelConfig, task["model"]))
        weights = {k: v for k, v in self._state["model"].items() if not k.startswith("planner.")}
        weights.update({f"planner.{k}": v for k, v in fresh.state_dict().items()})
        model = world_model_from_checkpoint({"model": weights, "config": {"task": task}}, self.cfg.world_model,
                                            PlannerTraining)
        model.requires_grad_(False)
        model.planner.requires_grad_(True)
        self._model = model
        return model

    def _cache(self, split: str, scenes: int) -> PlanCache:
        if self._model is None:
            raise RuntimeError("build_model() must run before the planner's windows are read")
        data = self.cfg.data
        windows = SyntheticDriving(split, scenes, data.frames_per_scene, stride=data.stride)
        cache = PlanCache(windows, self._model, data.cache_dir, planes=self.cfg.scene)
        if is_main():
            cache.build()
        barrier()
        return cache

    def train_dataset(self) -> PlanBatches:
        """The training windows, held on the model's device where they fit."""
        return self._cache("train", self.cfg.data.train_scenes).batches(next(self._model.parameters()).device)

    def collate(self, batch: PlanWindows) -> PlanWindows:
        return batch  # gathered already collated (PlanBatches)

    def samples_in(self, batch: PlanWindows) -> int:
        return batch.present.shape[0]

    def step_variant(self) -> bool:
        """Draws whether the next step mirrors its batch (``train.cuda_graph``: one graph each way)."""
        return self._mirror.draw()

    def training_step(self, model: nn.Module, batch: PlanWindows) -> tuple[Tensor, dict[str, Tensor]]:
        if self._mirror.take():
            batch = mirror_left_right(batch)
        command = drop_commands(batch.command, self.cfg.command_dropout, self._generator)
        plans, scores = model(batch.present, batch.previous, batch.past_actions, command)
        every = plan_error(plans, batch.future_actions.unsqueeze(1))  # [B, modes, S]
        rows = torch.arange(every.shape[0], device=every.device)
        winner = every.mean(2).argmin(1)  # the mode closest to this future learns it
        errors = every[rows, winner]
        distance = errors.mean()
        miss = (1 - torch.exp(-0.5 * (errors / self.cfg.precision_scale).square())).mean()
        base = plan_error(constant_turn_rate(batch.past_actions, plans.shape[2]), batch.future_actions)
        loss = distance + self.cfg.precision_weight * miss
        values = {"plan_l2": every[rows, scores.argmax(1)].mean().detach(), "ctr_l2": base.mean().detach(),
                  "plan_miss": miss.detach()}
        if plans.shape[1] > 1:  # the scores learn which mode wins
            choice = F.cross_entropy(scores, winner)
            loss = loss + choice
            values.update(closest_l2=distance.detach(), mode_choice=choice.detach())
        return loss, values

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        """On every validation window: L2 at 3 s and mean-L2 of the plans with and without the
        route command and of constant turn rate; ``score`` is minus the mean of the two mean-L2s
        (the planner must plan well with and without a command)."""
        if self._val is None:
            self._val = self._cache("val", self.cfg.data.val_scenes).all()
        device = next(model.parameters()).device
        val = self._val.to(device)
        steps = val.future_actions.shape[1]
        values: dict[str, float] = {}
        for name, command in (("command", val.command), ("no_command", None)):
            planned = model.planner(val.present, val.previous, val.past_actions, command)
            summary = plan_summary(plan_error(planned, val.future_actions))
            values.update({f"{name}_{k}": v for k, v in summary.items()})
        ctr = plan_summary(plan_error(constant_turn_rate(val.past_actions, steps), val.future_actions))
        values.update({f"ctr_{k}": v for k, v in ctr.items()})
        for name in ("command", "no_command"):
            for k in ("l2_3s", "l2_mean"):
                values[f"{name}_{k}_ratio"] = values[f"{name}_{k}"] / ctr[k]
        values["score"] = -(values["command_l2_mean"] + values["no_command_l2_mean"]) / 2
        return values

    def config_dict(self) -> dict:
        """The world model's own config with the planner's (the checkpoints are world-model
        checkpoints)."""
        task = copy.deepcopy(self._state["config"]["task"])
        task["model"].update(route_scene=self.cfg.scene, route_modes=self.cfg.modes)
        return task
