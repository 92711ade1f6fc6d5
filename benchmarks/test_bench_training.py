"""One stage-1 training step (small autoencoder, batch 2, sampled points) with the fused
decoder versus the reference decoder, inside the same task and optimiser; the ratio is the
training-throughput gain (samples/s = 2 / time)."""

from __future__ import annotations

import pytest
import torch

from t3fast.data.synthetic import SyntheticFrames
from t3fast.training.autoencoder import AutoencoderTask, preset


@pytest.mark.parametrize("impl", ["fused", "reference"])
def test_stage1_training_step(benchmark, impl):
    benchmark.group = "stage-1 training step (small, batch 2)"
    cfg = preset("small")
    cfg.decoder_backend = impl
    task = AutoencoderTask(cfg)
    torch.manual_seed(0)
    model = task.build_model()
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    frames = SyntheticFrames("val", 1)
    labels = task.collate([frames[0], frames[20]])

    def step():
        loss, _ = task.training_step(model, labels)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    benchmark.pedantic(step, rounds=5, warmup_rounds=1)
    benchmark.extra_info["samples_per_s"] = 2 / benchmark.stats.stats.median
