"""Settings that would crash a run late or quietly ruin it are refused when the config loads,
naming the dotted key and the value."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from t3fast.commands.main import main
from t3fast.errors import ConfigError
from t3fast.io.config import load_config
from t3fast.training.configs import Stage1Config, Stage2Config
from t3fast.training.trainer import Trainer
from tests.training.test_trainer import ToyTask, toy_config


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.grad_clip=-1", "train.grad_clip must be >= 0 (0 disables clipping), got -1.0"),
        ("train.grad_clip=nan", "train.grad_clip must be >= 0 (0 disables clipping), got nan"),
        ("train.lr=0", "train.lr must be a number > 0, got 0.0"),
        ("train.lr=-1e-3", "train.lr must be a number > 0, got -0.001"),
        ("train.lr=inf", "train.lr must be a number > 0, got inf"),
        ("train.min_lr=-1e-6", "train.min_lr must be between 0 and train.lr (0.001), got -1e-06"),
        ("train.min_lr=0.01", "train.min_lr must be between 0 and train.lr (0.001), got 0.01"),
        ("train.weight_decay=-0.1", "train.weight_decay must be >= 0 (0 turns it off), got -0.1"),
        ("train.steps=-5", "train.steps must be at least 1, got -5"),
        ("train.batch_size=0", "train.batch_size must be at least 1, got 0"),
        ("train.warmup_steps=-1", "train.warmup_steps must be at least 0, got -1"),
        ("loss.lovasz_weight=-1", "loss.lovasz_weight must be >= 0 (0 turns the term off), got -1.0"),
        ("loss.num_occupied=-1", "loss.num_occupied must be at least 0, got -1"),
        ("loss.class_weight_frames=0", "loss.class_weight_frames must be at least 1, got 0"),
        ("data.val_stride=0", "data.val_stride must be at least 1, got 0"),
    ],
)
def test_stage1_refuses(override, message):
    with pytest.raises(ConfigError) as info:
        load_config(Stage1Config, {"train": {"lr": 1e-3}}, [override])
    assert str(info.value) == message


@pytest.mark.parametrize(
    ("override", "message"),
    [
        *[(f"loss.{key}=-0.5", f"loss.{key} must be >= 0 (0 turns the term off), got -0.5")
          for key in ("gamma", "xi", "action_weight", "lovasz_weight")],
        ("loss.rollout_steps=0", "loss.rollout_steps must be in [1, 6], got 0"),
        ("loss.rollout_steps=7", "loss.rollout_steps must be in [1, 6], got 7"),
        ("loss.num_changed=-1", "loss.num_changed must be at least 0, got -1"),
        ("decoder_lr_scale=-0.1", "decoder_lr_scale must be >= 0 (0 freezes that part), got -0.1"),
        ("planner_lr_scale=nan", "planner_lr_scale must be >= 0 (0 freezes that part), got nan"),
        ("data.stride=0", "data.stride must be at least 1, got 0"),
        ("train.grad_clip=-1", "train.grad_clip must be >= 0 (0 disables clipping), got -1.0"),
    ],
)
def test_stage2_refuses(override, message):
    with pytest.raises(ConfigError) as info:
        load_config(Stage2Config, None, [override])
    assert str(info.value) == message


def test_limits_themselves_are_accepted():
    cfg = load_config(Stage2Config, None, ["train.grad_clip=0", "train.min_lr=0", "train.lr=1e-3", "train.min_lr=1e-3",
                                           "loss.xi=0", "loss.gamma=0", "decoder_lr_scale=0", "train.grad_clip=null",
                                           "loss.rollout_steps=6", "train.weight_decay=0"])
    assert cfg.train.grad_clip is None and cfg.train.min_lr == cfg.train.lr
    assert load_config(Stage1Config, None, ["train.grad_clip=0", "loss.lovasz_weight=0"]).train.grad_clip == 0


def test_grad_clip_zero_trains_unclipped(tmp_path):
    """0 disables clipping like null: the weights must move (a max norm of 0 would zero every gradient)."""
    torch.manual_seed(0)
    results = {}
    for clip in (0.0, None):
        trainer = Trainer(ToyTask(stochastic=False), toy_config(tmp_path / str(clip), grad_clip=clip, weight_decay=0.0))
        before = [p.detach().clone() for p in trainer.module.parameters()]
        trainer.fit()
        moved = any(not torch.equal(a, b) for a, b in zip(before, trainer.module.parameters()))
        results[clip] = (moved, nn.utils.parameters_to_vector(trainer.module.parameters()))
    assert results[0.0][0] and torch.equal(results[0.0][1], results[None][1])


def test_cli_prints_the_key_in_one_line(tmp_path, capsys):
    argv = ["train-ae", "--config", "small", "train.steps=1", "train.eval_every=0", "train.grad_clip=-1"]
    assert main([*argv, f"train.out_dir={tmp_path / 'r'}"]) == 1
    assert capsys.readouterr().err == (
        "t3fast train-ae: train.grad_clip must be >= 0 (0 disables clipping), got -1.0\n"
    )
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.seed=1e30", "train.seed must be an integer in [0, 2**63), got 1000000000000000019884624838656"),
        ("train.seed=-1", "train.seed must be an integer in [0, 2**63), got -1"),
        ("train.device=tpu", "train.device must be 'auto', 'cuda' or 'cpu', got 'tpu'"),
        ("train.device=cuda:7", "train.device must be 'auto', 'cuda' or 'cpu', got 'cuda:7' (each process "
                                "trains on one GPU: choose it with CUDA_VISIBLE_DEVICES=7)"),
    ],
)
def test_seed_and_device_are_checked(override, message):
    with pytest.raises(ConfigError) as info:
        load_config(Stage1Config, None, [override])
    assert str(info.value) == message


def test_largest_seed_is_accepted(tmp_path):
    cfg = load_config(Stage1Config, None, [f"train.seed={2**63 - 1}"])
    assert Trainer(ToyTask(), toy_config(tmp_path, seed=cfg.train.seed)).fit()["step"] == 8


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_cuda_names_the_key(tmp_path):
    with pytest.raises(ConfigError) as info:
        Trainer(ToyTask(), toy_config(tmp_path / "run", device="cuda"))
    assert str(info.value) == "train.device is 'cuda' but CUDA is not available here: use train.device=cpu (or auto)"
    assert not (tmp_path / "run").exists()


def test_a_process_without_its_gpu_names_the_key(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setenv("LOCAL_RANK", "3")
    with pytest.raises(ConfigError) as info:
        Trainer(ToyTask(), toy_config(tmp_path / "run", device="cuda"))
    assert str(info.value) == ("train.device is 'cuda' but this process (LOCAL_RANK=3) needs GPU 3 and 2 are "
                               "visible: start at most 2 processes per machine")
