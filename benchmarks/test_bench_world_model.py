"""The world model's forecasting step at batch 1 (the agents' velocities for a tracker prior,
forecaster, planner, decoding the 6 future frames to labels, from encoded past frames) with the
compiled operators versus their pure-PyTorch references (decoder and delta fusion), same
untrained weights; FPS = 1 / time. ``wm-small`` is the shipped design (the flow forecaster from
the tracker's velocities), ``wm-small-delta`` the papers' Delta forecaster."""

from __future__ import annotations

import pytest
import torch

import t3fast.models.flow_forecaster as flow_module
import t3fast.models.forecaster as forecaster_module
from t3fast.data.classes import CAR, FREE
from t3fast.models.world_model import T3Former
from t3fast.ops import delta_fuse, reference
from t3fast.presets import autoencoder_size, preset


@pytest.mark.parametrize("name", ["wm-small", "wm-small-delta"])
@pytest.mark.parametrize("impl", ["fused", "reference"])
def test_forecasting_step(benchmark, impl, name, monkeypatch):
    benchmark.group = f"world model forecasting step ({name}, batch 1)"
    torch.manual_seed(0)
    model = T3Former.from_config(autoencoder_size("small"), preset(name).model).eval()
    model.decoder.backend = impl
    fuse = delta_fuse if impl == "fused" else reference.delta_fuse
    for module in (forecaster_module, flow_module):
        monkeypatch.setattr(module, "delta_fuse", fuse)
    occ = torch.full((1, 5, 200, 200, 16), FREE, dtype=torch.uint8)
    for t in range(5):  # a few cars driving along x, so the tracker has agents to measure
        for lane in range(4):
            occ[0, t, 40 + 3 * t + 30 * lane : 50 + 3 * t + 30 * lane, 60 + 20 * lane : 64 + 20 * lane, 0:4] = CAR
    pipeline = model.pipeline
    past = pipeline.encode(occ, torch.zeros(1, 4, 2))  # a standing ego

    def step() -> None:  # the agents (the tracker, the box fits), the forecast, the plan, the render
        pipeline.from_past(past, None, 6, None)

    benchmark.pedantic(step, rounds=5, warmup_rounds=1)
    benchmark.extra_info["fps"] = 1 / benchmark.stats.stats.median
