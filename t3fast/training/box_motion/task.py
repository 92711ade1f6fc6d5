"""The box motion network's own :class:`~t3fast.training.task.Task`: a trained world model that
draws its agents as fitted boxes gets a :class:`~t3fast.models.box_motion.BoxMotionNet`, trained
on many cached windows (:mod:`t3fast.training.box_motion.box_cache`), everything else frozen.

The loss is each agent's landing error (:func:`~t3fast.training.box_motion.loss.landing_errors`:
metres between its predicted and true box at every future step), averaged per class and then
over the classes (:func:`~t3fast.training.box_motion.loss.class_balanced_mean`), with agents
mirrored left-right at random. ``best.pt`` follows the same error on windows of held-out
training-split scenes; each evaluation also scores the box tracker (the network at zero: the
fitted constant velocity) on them. Checkpoints are whole world models with
``model.box_motion = true``: ``t3fast eval`` and ``t3fast export`` take them as they are.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn

from t3fast.agents.box_kinematics import corrected_motion, mirror_kinematics, mirror_views
from t3fast.data.synthetic import SyntheticDriving
from t3fast.data.synthetic.dataset import SPLIT_SIZE
from t3fast.device_constants import device_constant
from t3fast.errors import ConfigError
from t3fast.evaluation.planning import HORIZONS as STEPS_AT
from t3fast.io.checkpoint import WORLD_MODEL, read_checkpoint
from t3fast.models.box_motion import BoxMotionNet
from t3fast.models.ego_motion import rotate
from t3fast.models.world_model import T3Former
from t3fast.pretrained import resolve, world_model_from_checkpoint
from t3fast.training.box_motion.box_cache import BoxCache, BoxMotionSamples
from t3fast.training.box_motion.loss import class_balanced_mean, landing_errors
from t3fast.training.configs import BoxDataConfig, BoxMotionConfig
from t3fast.training.distributed import barrier, is_main
from t3fast.training.step_draws import uniform

VAL_CHUNK = 4096  # agents per forward pass in evaluation


def mirror_agents(batch: dict[str, Tensor], flip: Tensor) -> dict[str, Tensor]:
    """The agents of ``batch`` where ``flip`` ``[n]`` (bool) is set mirrored across their own
    heading line: views, kinematics, fitted velocity, true displacements and turns (the heading
    stays)."""
    out = dict(batch)
    out["views"] = torch.where(flip[:, None, None, None], mirror_views(batch["views"]), batch["views"])
    out["features"] = torch.where(flip[:, None], mirror_kinematics(batch["features"]), batch["features"])
    for key in ("velocity", "displacement"):
        value = batch[key]
        shape = (-1,) + (1,) * (value.dim() - 2)
        heading = batch["heading"].view(shape).expand(value.shape[:-1])
        local = rotate(value, -heading)
        mirrored = local * device_constant((1.0, -1.0), local.dtype, local.device)
        local = torch.where(flip.view(*shape, 1), mirrored, local)
        out[key] = rotate(local, heading)
    out["turn"] = torch.where(flip[:, None], -batch["turn"], batch["turn"])
    return out


def agent_errors(correction: Tensor, batch: dict[str, Tensor]) -> Tensor:
    """Per agent and step ``[n, S]``, the landing error of the boxes moved by ``correction``."""
    displacement, turn = corrected_motion(batch["velocity"], batch["heading"], correction)
    return landing_errors(displacement, turn, batch)


def check_scene_count(data: BoxDataConfig) -> None:
    """The training and the held-out scenes, taken one after the other from the synthetic train
    split, fit in it."""
    if data.train_scenes + data.select_scenes > SPLIT_SIZE:
        raise ConfigError(f"data.train_scenes + data.select_scenes must be at most {SPLIT_SIZE:,} (the scenes of the "
                          f"synthetic train split), got {data.train_scenes} + {data.select_scenes}")


class BoxMotionTraining(T3Former):
    """The world model as the box motion network's training sees it (and DDP wraps): its
    forward is that network's."""

    def forward(self, views: Tensor, features: Tensor) -> Tensor:
        """:class:`~t3fast.models.box_motion.BoxMotionNet`'s corrections of the agents."""
        return self.box_motion(views, features)


class BoxMotionTask:
    """Trains a box motion network for ``cfg.world_model`` alone (see the module doc)."""

    def __init__(self, cfg: BoxMotionConfig):
        check_scene_count(cfg.data)
        self.cfg = copy.deepcopy(cfg)
        self._state = read_checkpoint(resolve(self.cfg.world_model), WORLD_MODEL)
        if not self._state["config"]["task"].get("model", {}).get("agent_boxes"):
            raise ConfigError(f"world_model {self.cfg.world_model!r} does not draw fitted boxes: train-box-motion "
                              "needs model.agent_boxes = true")
        self._model: nn.Module | None = None
        self._select: BoxMotionSamples | None = None
        self._generator = torch.Generator().manual_seed(self.cfg.train.seed)

    def build_model(self) -> nn.Module:
        """The world model with a new box motion network (zero correction: the box tracker);
        every other weight from ``cfg.world_model``, frozen."""
        model = world_model_from_checkpoint(self._state, self.cfg.world_model, BoxMotionTraining)
        model.requires_grad_(False)
        model.box_motion = BoxMotionNet(model.forecaster.history, model.forecaster.steps)
        self._model = model
        return model

    def _samples(self, first: int, count: int, name: str, device: torch.device) -> BoxMotionSamples:
        """The agents of ``count`` scenes from scene ``first``, held on ``device`` where they fit."""
        data = self.cfg.data
        windows = SyntheticDriving("train", first + count, data.frames_per_scene, stride=data.stride)
        cache = BoxCache(windows, data.cache_dir, range(first, first + count), desc=f"box fits ({name})")
        # rank 0 fits (or reads) the records; the others read what it wrote
        records = cache.records() if is_main() else None
        barrier()
        return BoxMotionSamples(records if records is not None else cache.records(progress=False), device)

    def train_dataset(self) -> BoxMotionSamples:
        if self._model is None:
            raise RuntimeError("build_model() must run before the agents are read")
        return self._samples(0, self.cfg.data.train_scenes, "train", next(self._model.parameters()).device)

    def collate(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        return batch  # gathered already collated (BoxMotionSamples)

    def samples_in(self, batch: dict[str, Tensor]) -> int:
        return batch["views"].shape[0]

    def step_variant(self) -> None:
        """No host-side choice (``train.cuda_graph``): where the host may not read, the agents to
        mirror are drawn on the device."""
        return None

    def training_step(self, model: nn.Module, batch: dict[str, Tensor]) -> tuple[Tensor, dict[str, Tensor]]:
        flip = uniform((self.samples_in(batch),), batch["views"].device, self._generator) < 0.5
        batch = mirror_agents(batch, flip)
        correction = model(batch["views"].float(), batch["features"])
        loss = class_balanced_mean(agent_errors(correction, batch), batch)
        with torch.no_grad():
            tracker = class_balanced_mean(agent_errors(torch.zeros_like(correction), batch), batch)
        return loss, {"tracker": tracker}

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        """On the held-out scenes' agents, the class-balanced landing error (metres) of the
        network's boxes and of the box tracker's, over all steps and at 1, 2 and 3 s;
        ``ratio``: network / tracker; ``score``: minus the network's error."""
        device = next(model.parameters()).device
        if self._select is None:
            self._select = self._samples(self.cfg.data.train_scenes, self.cfg.data.select_scenes, "select", device)
        fields = {k: v.to(device) for k, v in self._select.fields.items() if k != "views"}
        views = self._select.fields["views"]
        corrections = torch.cat([model.box_motion(views[i : i + VAL_CHUNK].to(device).float(),
                                                  fields["features"][i : i + VAL_CHUNK])
                                 for i in range(0, len(self._select), VAL_CHUNK)])
        values = {}
        for name, correction in (("net", corrections), ("tracker", torch.zeros_like(corrections))):
            errors = agent_errors(correction, fields)
            values[name] = class_balanced_mean(errors, fields).item()
            for horizon, steps in STEPS_AT.items():
                at = {"features": fields["features"], "valid": fields["valid"][:, steps - 1 : steps]}
                values[f"{name}_{horizon}"] = class_balanced_mean(errors[:, steps - 1 : steps], at).item()
        values["ratio"] = values["net"] / max(values["tracker"], 1e-9)
        values["score"] = -values["net"]
        return values

    def config_dict(self) -> dict:
        """The world model's config with ``model.box_motion`` on (checkpoints are world-model
        checkpoints)."""
        config = copy.deepcopy(self._state["config"]["task"])
        config["model"]["box_motion"] = True
        return config
