"""The Delta forecaster's stage-2 loss on cached ego-aligned windows: what it weighs, what it
logs, and that the forecaster learns from it."""

from __future__ import annotations

import json

import pytest
import torch
from torch import nn

from t3fast.commands.main import main
from t3fast.data.sample import PRESENT, WINDOW
from t3fast.models.triplane import Triplane
from t3fast.pretrained import load_world_model
from t3fast.training.configs import WorldLossConfig
from t3fast.training.world_model.delta_loss import delta_rollout_loss
from t3fast.training.world_model.forwards import RolloutModel
from t3fast.training.world_model.latent_cache import AlignedBatch

from ..models.test_world_model import tiny_world_model
from .test_world_model_task import shifting_sequence
from .tiny_runs import TINY_WM


def _batch(planes: Triplane, boxes: torch.Tensor | None = None) -> AlignedBatch:
    b = planes.xy.shape[0]
    if boxes is None:
        boxes = torch.zeros(b, WINDOW, 1, 7)
    valid = torch.ones(boxes.shape[:3], dtype=torch.bool) if boxes.abs().sum() else torch.zeros(boxes.shape[:3],
                                                                                                 dtype=torch.bool)
    future = torch.tensor([[[1.0, 0.0]] * 6]).expand(b, -1, -1)
    return AlignedBatch(planes, boxes, valid, torch.zeros(b, 4, 2), future, torch.zeros(b, 4, *planes.xy.shape[-2:]))


class _Offset(nn.Module):
    """Predicts the true next planes with ``offset`` added to the xy plane, and a planner that
    is frozen (or not) and always predicts zero displacement."""

    def __init__(self, truth: Triplane, offset: torch.Tensor, planner_trains: bool):
        super().__init__()
        self.truth, self.offset = truth, offset
        self.planner = nn.Linear(1, 1).requires_grad_(planner_trains)

    def forward(self, history, actions, steps, first):
        t = PRESENT + 1 + first
        futures = [Triplane(self.truth.xy[:, t + j] + self.offset, self.truth.xz[:, t + j], self.truth.yz[:, t + j])
                   for j in range(steps)]
        return futures, torch.zeros(self.truth.xy.shape[0], steps, 2), None


def _planes(b: int = 1, h: int = 100, w: int = 100) -> Triplane:
    torch.manual_seed(0)
    return Triplane(torch.randn(b, WINDOW, 2, h, w), torch.randn(b, WINDOW, 2, h, 8), torch.randn(b, WINDOW, 2, w, 8))


def test_an_agents_cells_weigh_one_plus_agent_weight():
    """The same error costs ``1 + agent_weight`` times as much on a cell an agent's box covers."""
    planes = _planes()
    box = torch.tensor([0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])  # a parked car at the ego's cell
    batch = _batch(planes, box.expand(1, WINDOW, 1, 7).clone())
    cfg = WorldLossConfig(agent_weight=20.0, gamma=0.0, rollout_steps=1, pushforward=False)
    losses = []
    for cell in ((50, 50), (10, 10)):  # under the car, far from it
        offset = torch.zeros(2, 100, 100)
        offset[:, cell[0], cell[1]] = 1.0
        losses.append(float(delta_rollout_loss(_Offset(planes, offset, False), batch, cfg, first=2)[1]["latent"]))
    assert losses[0] == pytest.approx(21 * losses[1], rel=1e-4)


def test_the_total_is_what_the_gradient_sees():
    planes = _planes()
    cfg = WorldLossConfig(rollout_steps=2, action_weight=3.0, pushforward=False)
    for trains in (False, True):
        total, parts = delta_rollout_loss(_Offset(planes, torch.zeros(()), trains), _batch(planes), cfg, first=1)
        assert parts["latent"] == pytest.approx(0.0, abs=1e-6) and parts["action"] == pytest.approx(1.0)
        assert float(total) == pytest.approx(3.0 if trains else 0.0)  # a frozen planner's error is only logged
        assert parts["copy_latent"] > 0.5


def test_a_rollout_must_end_within_the_window():
    planes = _planes()
    with pytest.raises(ValueError, match="starts at a future step in \\[0, 4\\], got 5"):
        delta_rollout_loss(_Offset(planes, torch.zeros(()), False), _batch(planes), WorldLossConfig(rollout_steps=2),
                           first=5)


def test_the_untrained_forecaster_is_the_copy_forecast_and_learns_below_it():
    """Delta starts at 0 (the copy of the last history frame), so from step 0 its latent loss is
    the copy forecast's; trained on the moving box it falls well below it, with and without
    pushforward."""
    for pushforward in (False, True):
        model = tiny_world_model(RolloutModel).train()
        planes = model.encode_sequence(shifting_sequence())
        batch = _batch(planes)
        cfg = WorldLossConfig(rollout_steps=1, pushforward=pushforward)
        _, parts = delta_rollout_loss(model, batch, cfg, first=0)
        assert float(parts["latent"]) == pytest.approx(float(parts["copy_latent"]), rel=1e-5)
        opt = torch.optim.Adam([p for p in model.forecaster.parameters() if p.requires_grad], lr=3e-3)
        for step in range(60):
            loss, _ = delta_rollout_loss(model, batch, cfg, first=step % 6)
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            after = [delta_rollout_loss(model, batch, cfg, first=k)[1] for k in range(6)]
        assert sum(p["latent"] for p in after) < 0.5 * sum(p["copy_latent"] for p in after)


def test_ablation_presets_train_on_the_aligned_cache(world_ckpt, tmp_path):
    """An ego-aligned Delta ablation reads the windows the flow forecaster's cache holds (same
    encoder: no new cache) and logs the latent loss next to the copy forecast's."""
    cache = world_ckpt.parent.parent / "cache"
    before = sorted(p.name for p in cache.glob("aligned-*"))
    out = tmp_path / "no-delta"
    assert main(["train-wm", "--config", "small-no-delta", "--ae", str(world_ckpt.parent.parent / "ae" / "last.pt"),
                 f"data.cache_dir={cache}", f"train.out_dir={out}", *TINY_WM, "train.steps=2",
                 "train.eval_every=0"]) == 0
    assert sorted(p.name for p in cache.glob("aligned-*")) == before
    train = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    values = [e["values"] for e in train if e["event"] == "train"][-1]
    assert {"latent", "copy_latent", "action"} <= set(values) and values["loss"] == pytest.approx(values["latent"])
    assert not load_world_model(out / "last.pt").world_config.predict_delta
