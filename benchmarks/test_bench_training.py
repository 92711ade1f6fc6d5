"""Training steps. Stage 1 (small autoencoder, batch 2, sampled points) with the fused decoder
versus the reference decoder, inside the same task and optimiser; the ratio is the
training-throughput gain (samples/s = 2 / time). Stage 2 (the world model, batch 1) with and
without encoding only the frames a rollout reads, and stage-2 samples per CPU-minute of the
Delta forecaster's step against the flow forecaster's on cached windows."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving, SyntheticFrames
from t3fast.forecast.agents import measured_velocities
from t3fast.models.ego_motion import planar_poses
from t3fast.models.triplane import Triplane
from t3fast.presets import autoencoder_size, preset, world_model_size
from t3fast.training.autoencoder.task import AutoencoderTask
from t3fast.training.configs import WorldLossConfig
from t3fast.training.world_model.forwards import FlowMotionModel, RolloutModel
from t3fast.training.world_model.latent_cache import AlignedWindow, collate_aligned
from t3fast.training.world_model.loss import rollout_loss
from t3fast.training.world_model.motion_loss import motion_loss
from t3fast.training.world_model.windows import collate_windows, ego_aligned_window, moved_window, rollout_frames


@pytest.mark.parametrize("impl", ["fused", "reference"])
def test_stage1_training_step(benchmark, impl):
    benchmark.group = "stage-1 training step (small, batch 2)"
    cfg = preset("ae-small")
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


@pytest.mark.parametrize("encode", ["rollout frames", "all frames", "cached planes"])
def test_stage2_training_step(benchmark, encode):
    """One stage-2 step of the ``small`` preset (ego-aligned window, one-step rollout from
    future step 3 with pushforward, backward, AdamW): encoding only the frames the rollout
    reads versus all 11 frames of the window, versus the planes read from the aligned cache
    (``data.cache_labels``: encoded once, stored in float16; the labels moved in the step)."""
    benchmark.group = "stage-2 training step (small, batch 1)"
    torch.manual_seed(0)
    world = dataclasses.replace(world_model_size("small"), ego_aligned=True)
    model = RolloutModel.from_config(autoencoder_size("small"), world).train()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    batch = collate_windows([SyntheticDriving("val", 1, 20, stride=9)[0]])
    loss_cfg = WorldLossConfig(rollout_steps=1)
    first = 3
    frames = rollout_frames(first, 1, loss_cfg.pushforward) if encode == "rollout frames" else None
    cached = ego_aligned_window(model, batch.occ, batch.ego_poses)[0].map(lambda p: p.half().float())

    def step():
        if encode == "cached planes":
            planes, occ = cached, moved_window(batch.occ, batch.ego_poses)
        else:
            planes, occ = ego_aligned_window(model, batch.occ, batch.ego_poses, frames)
        loss, _ = rollout_loss(model, planes, occ, batch.past_actions, batch.future_actions, first, 1, loss_cfg)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    benchmark.pedantic(step, rounds=3, warmup_rounds=1)
    benchmark.extra_info["samples_per_s"] = 1 / benchmark.stats.stats.median


def _flow_step(batch_size: int):
    """The ``small`` preset's step (flow forecaster, batch 8): cached ego-aligned windows in, the
    motion loss, backward, AdamW. The windows are encoded once, outside the timed step, as the
    cache does."""
    cfg = preset("wm-small")
    model = FlowMotionModel.from_config(autoencoder_size("small"), cfg.model).train()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    planes, _ = ego_aligned_window(model, sample.occ[None], sample.ego_poses[None])
    poses = planar_poses(sample.ego_poses[None, : PRESENT + 1], PRESENT)
    velocity = measured_velocities(sample.occ[None, : PRESENT + 1], poses, model.encoder.config.plane_shape[:2])
    window = AlignedWindow(Triplane(*(p[0] for p in planes)), sample.boxes, sample.box_valid, sample.past_actions,
                           sample.future_actions, velocity[0])
    batch = collate_aligned([window] * batch_size)

    def step():
        loss, _ = motion_loss(model, batch, cfg.loss)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return step


def _delta_step():
    """The step the ``small-delta`` preset trains with (the papers' forecaster, batch 1): the
    window moved into the present frame and encoded in the step, a one-step pushforward rollout."""
    cfg = preset("wm-small-delta")
    model = RolloutModel.from_config(autoencoder_size("small"), cfg.model).train()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    batch = collate_windows([SyntheticDriving("val", 1, 20, stride=9)[0]])
    first = 3
    frames = rollout_frames(first, 1, cfg.loss.pushforward)

    def step():
        planes, occ = ego_aligned_window(model, batch.occ, batch.ego_poses, frames)
        loss, _ = rollout_loss(model, planes, occ, batch.past_actions, batch.future_actions, first, 1, cfg.loss)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    return step


@pytest.mark.parametrize("trainer", ["flow, cached windows, batch 8", "delta, encoded in the step, batch 1"])
def test_stage2_samples_per_cpu_minute(benchmark, trainer):
    """Stage-2 throughput of the shipped model's training against the papers' forecaster's."""
    benchmark.group = "stage-2 samples per CPU-minute"
    torch.manual_seed(0)
    batch = 8 if trainer.startswith("flow") else 1
    step = _flow_step(batch) if batch > 1 else _delta_step()
    benchmark.pedantic(step, rounds=3, warmup_rounds=1)
    benchmark.extra_info["samples_per_minute"] = 60 * batch / benchmark.stats.stats.median
