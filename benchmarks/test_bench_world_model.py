"""The world model's forecasting step at batch 1 (forecaster, planner, decoding the 6 future
frames to labels, from encoded past frames) with the compiled operators versus their pure-PyTorch
references (decoder and delta fusion), same untrained weights; FPS = 1 / time."""

from __future__ import annotations

import pytest
import torch

import t3fast.models.forecaster as forecaster_module
from t3fast.models.world_model import T3Former
from t3fast.ops import delta_fuse, reference
from t3fast.presets import autoencoder_size, world_model_size


@pytest.mark.parametrize("impl", ["fused", "reference"])
def test_forecasting_step(benchmark, impl, monkeypatch):
    benchmark.group = "world model forecasting step (small, batch 1)"
    torch.manual_seed(0)
    model = T3Former.from_config(autoencoder_size("small"), world_model_size("small")).eval()
    model.decoder.backend = impl
    monkeypatch.setattr(forecaster_module, "delta_fuse", delta_fuse if impl == "fused" else reference.delta_fuse)
    past = model.encode_sequence(torch.randint(0, 18, (1, 5, 200, 200, 16), dtype=torch.uint8))
    actions = torch.zeros(1, 4, 2)
    benchmark.pedantic(lambda: model.forecast_from_triplanes(past, actions), rounds=5, warmup_rounds=1)
    benchmark.extra_info["fps"] = 1 / benchmark.stats.stats.median
