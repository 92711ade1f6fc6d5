"""The generic trainer on a toy regression task: learning, schedule, data order, exact resume, Ctrl-C."""

from __future__ import annotations

import json
import math
import os
import random
import signal
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn
from torch.utils.data import Dataset, TensorDataset

from t3fast.io.checkpoint import load_checkpoint
from t3fast.training.batch_sampler import ResumableBatchSampler
from t3fast.training.configs import TrainConfig
from t3fast.training.param_groups import param_groups
from t3fast.training.schedule import warmup_cosine
from t3fast.training.trainer import Trainer


class ToyTask:
    """Noisy linear regression. ``stochastic`` adds dropout and draws from the python and numpy
    generators in every step, so a resume that fails to restore any random stream changes the weights."""

    def __init__(
        self, n: int = 24, dim: int = 4, stochastic: bool = True, on_step: Callable[[int], None] | None = None
    ) -> None:
        gen = torch.Generator().manual_seed(123)
        self.x = torch.randn(n, dim, generator=gen)
        self.y = self.x @ torch.randn(dim, 1, generator=gen) + 0.01 * torch.randn(n, 1, generator=gen)
        self.dim, self.stochastic, self.on_step = dim, stochastic, on_step
        self.calls = 0
        self.seen: list[torch.Tensor] = []  # the batches, in the order training used them

    def build_model(self) -> nn.Module:
        return nn.Sequential(nn.Linear(self.dim, 16), nn.Dropout(0.2 if self.stochastic else 0.0), nn.Linear(16, 1))

    def train_dataset(self) -> Dataset:
        return TensorDataset(self.x, self.y)

    def collate(self, batch_list: list[tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor]:
        xs, ys = zip(*batch_list)
        return torch.stack(xs), torch.stack(ys)

    def training_step(self, model: nn.Module, batch: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, dict]:
        self.calls += 1
        if self.on_step is not None:
            self.on_step(self.calls)
        x, y = batch
        self.seen.append(x.clone())
        loss = nn.functional.mse_loss(model(x), y)
        if self.stochastic:
            loss = loss * (1.0 + 1e-3 * random.random()) * (1.0 + 1e-3 * float(np.random.rand()))
        return loss, {"mse": float(loss.detach())}

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        torch.rand(3), random.random(), np.random.rand()  # must not disturb the training streams
        mse = float(nn.functional.mse_loss(model(self.x), self.y))
        return {"score": -mse, "mse": mse}

    def samples_in(self, batch: tuple[torch.Tensor, torch.Tensor]) -> int:
        return batch[0].shape[0]

    def config_dict(self) -> dict:
        return {"n": len(self.x), "dim": self.dim}


def toy_config(out_dir: Path, **kw) -> TrainConfig:
    base = TrainConfig(
        steps=8, batch_size=4, lr=0.05, warmup_steps=2, seed=7, log_every=1, eval_every=3, ckpt_every=4,
        out_dir=str(out_dir), tensorboard=False, device="cpu",
    )  # fmt: skip
    return replace(base, **kw)


def crash_at(call: int) -> Callable[[int], None]:
    def hook(n: int) -> None:
        if n == call:
            raise RuntimeError("simulated crash")

    return hook


def assert_same_training_state(a: Path, b: Path) -> None:
    sa, sb = load_checkpoint(a), load_checkpoint(b)
    assert sa["step"] == sb["step"]
    for k in sa["model"]:
        assert torch.equal(sa["model"][k], sb["model"][k]), k
    oa, ob = sa["optimizer"], sb["optimizer"]
    assert oa["param_groups"] == ob["param_groups"]
    for i in oa["state"]:
        for k in oa["state"][i]:
            assert torch.equal(oa["state"][i][k], ob["state"][i][k]), (i, k)
    assert sa["scheduler"] == sb["scheduler"]
    ra, rb = sa["rng"][0], sb["rng"][0]
    assert torch.equal(ra["torch"], rb["torch"]) and ra["python"] == rb["python"]
    assert torch.equal(ra["numpy"][1], rb["numpy"][1]) and ra["numpy"][2:] == rb["numpy"][2:]


def metric_events(out_dir: Path, event: str) -> list[dict]:
    lines = (out_dir / "metrics.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["event"] == event]


def test_schedule_warmup_peak_and_floor() -> None:
    lr, min_lr = 1e-3, 1e-6
    f = warmup_cosine(total_steps=100, warmup_steps=10, lr=lr, min_lr=min_lr)
    assert f(0) * lr == pytest.approx(lr / 11)  # the first step already learns
    assert all(f(s) < f(s + 1) for s in range(10))
    assert f(10) == pytest.approx(1.0)
    assert f(55) * lr == pytest.approx((lr + min_lr) / 2)  # half-way down the cosine
    assert all(f(s) > f(s + 1) for s in range(10, 100))
    assert f(100) * lr == pytest.approx(min_lr) and f(1000) * lr == pytest.approx(min_lr)
    with pytest.raises(ValueError):
        warmup_cosine(total_steps=5, warmup_steps=10, lr=lr)


def test_sampler_shards_global_batches_and_resumes_mid_epoch() -> None:
    def batches(rank: int, world: int, epoch: int, skip: int = 0, batch: int = 2) -> list[list[int]]:
        s = ResumableBatchSampler(10, batch, seed=3, rank=rank, world_size=world)
        s.set_epoch(epoch, skip)
        return list(s)

    single = batches(0, 1, epoch=0, batch=4)  # two global batches of 4, tail of 2 dropped
    r0, r1 = batches(0, 2, epoch=0), batches(1, 2, epoch=0)
    assert len(single) == len(r0) == len(r1) == 2
    assert [a + b for a, b in zip(r0, r1)] == single  # ranks split each global batch
    assert batches(0, 2, epoch=0, skip=1) == r0[1:]
    assert batches(0, 2, epoch=1) != r0 and batches(0, 2, epoch=0) == r0
    with pytest.raises(ValueError, match="smaller than one global batch"):
        ResumableBatchSampler(3, 2, seed=0, world_size=2)


def test_weight_decay_skips_biases_norms_embeddings_and_frozen() -> None:
    model = nn.Sequential(nn.Embedding(5, 3), nn.Linear(3, 3), nn.LayerNorm(3), nn.Conv1d(3, 3, 1))
    model[3].weight.requires_grad_(False)
    decay, no_decay = param_groups(model, 0.01)
    assert decay["weight_decay"] == 0.01 and no_decay["weight_decay"] == 0.0
    assert {id(p) for p in decay["params"]} == {id(model[1].weight)}
    exempt = [model[0].weight, model[1].bias, model[2].weight, model[2].bias, model[3].bias]
    assert {id(p) for p in no_decay["params"]} == {id(p) for p in exempt}


def test_lr_scales_give_submodules_their_own_rate() -> None:
    model = nn.Sequential(nn.Linear(3, 3), nn.Sequential(nn.Linear(3, 3)))
    groups = param_groups(model, 0.01, lr=1e-3, lr_scales={"1": 0.1})
    assert [(g["lr"], g["weight_decay"]) for g in groups] == [(1e-3, 0.01), (1e-3, 0.0), (1e-4, 0.01), (1e-4, 0.0)]
    assert {id(p) for g in groups[2:] for p in g["params"]} == {id(p) for p in model[1].parameters()}
    # the scheduler scales every group's own rate
    opt = torch.optim.AdamW(groups, lr=1e-3)
    torch.optim.lr_scheduler.LambdaLR(opt, lambda step: 0.5)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([5e-4, 5e-4, 5e-5, 5e-5])


def test_training_lowers_the_loss_and_writes_outputs(tmp_path: Path) -> None:
    task = ToyTask(stochastic=False)
    cfg = toy_config(tmp_path, steps=60, log_every=10, eval_every=20, ckpt_every=30)
    trainer = Trainer(task, cfg)
    with torch.no_grad():
        start_mse = task.evaluate(trainer.module)["mse"]
    result = trainer.fit()
    assert result["step"] == 60 and not trainer.interrupted
    assert result["eval/mse"] < 0.1 * start_mse
    assert math.isfinite(result["train/samples_per_s"]) and result["train/lr"] > 0

    train, evals = metric_events(tmp_path, "train"), metric_events(tmp_path, "eval")
    assert [r["step"] for r in train] == [10, 20, 30, 40, 50, 60]
    assert [r["step"] for r in evals] == [20, 40, 60]
    assert {"loss", "mse", "lr", "grad_norm", "samples_per_s"} <= set(train[0]["values"])
    best = load_checkpoint(tmp_path / "best.pt")
    assert best["best_score"] == max(r["values"]["score"] for r in evals)
    last = load_checkpoint(tmp_path / "last.pt")
    assert last["step"] == 60 and last["config"]["task"] == {"n": 24, "dim": 4}
    assert last["config"]["train"]["steps"] == 60


def test_resume_after_crash_is_bit_identical(tmp_path: Path) -> None:
    straight_task = ToyTask()
    Trainer(straight_task, toy_config(tmp_path / "straight")).fit()

    out = tmp_path / "resumed"
    with pytest.raises(RuntimeError, match="simulated crash"):
        Trainer(ToyTask(on_step=crash_at(6)), toy_config(out)).fit()  # dies in step 6; last.pt is step 4
    assert load_checkpoint(out / "last.pt")["step"] == 4
    resumed_task = ToyTask()
    trainer = Trainer(resumed_task, toy_config(out, resume=True))
    assert trainer.step == 4
    trainer.fit()

    assert_same_training_state(tmp_path / "straight" / "last.pt", out / "last.pt")
    # the same batches in the same order (the epoch of 6 batches ends at step 6)
    assert all(torch.equal(a, b) for a, b in zip(straight_task.seen[4:], resumed_task.seen, strict=True))
    # events the crashed run logged after its checkpoint are dropped on resume
    assert [r["step"] for r in metric_events(out, "train")] == list(range(1, 9))


def test_sigint_saves_last_and_resumes_identically(tmp_path: Path) -> None:
    Trainer(ToyTask(), toy_config(tmp_path / "straight", ckpt_every=0)).fit()

    def interrupt(n: int) -> None:
        if n == 2:
            os.kill(os.getpid(), signal.SIGINT)

    out = tmp_path / "interrupted"
    before = signal.getsignal(signal.SIGINT)
    trainer = Trainer(ToyTask(on_step=interrupt), toy_config(out, ckpt_every=0))
    result = trainer.fit()
    assert trainer.interrupted and result["step"] == 2
    assert signal.getsignal(signal.SIGINT) is before
    assert load_checkpoint(out / "last.pt")["step"] == 2
    assert not (out / "best.pt").exists()  # stopped before the first evaluation

    resumed = Trainer(ToyTask(), toy_config(out, ckpt_every=0, resume_from=str(out / "last.pt")))
    assert resumed.fit()["step"] == 8 and not resumed.interrupted
    assert_same_training_state(tmp_path / "straight" / "last.pt", out / "last.pt")


def test_evaluation_does_not_change_training(tmp_path: Path) -> None:
    Trainer(ToyTask(), toy_config(tmp_path / "eval", eval_every=1)).fit()
    Trainer(ToyTask(), toy_config(tmp_path / "no_eval", eval_every=0)).fit()
    assert not (tmp_path / "no_eval" / "best.pt").exists()
    assert_same_training_state(tmp_path / "eval" / "last.pt", tmp_path / "no_eval" / "last.pt")


def test_resume_from_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        Trainer(ToyTask(), toy_config(tmp_path, resume_from=str(tmp_path / "nope.pt")))
