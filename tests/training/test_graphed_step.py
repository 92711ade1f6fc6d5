"""Training steps replayed from CUDA graphs (``train.cuda_graph``). On the CPU the same step runs
from the static buffers without a graph, so everything but the capture is checked there; the
``cuda`` cases capture and replay."""

from __future__ import annotations

import json
from collections import namedtuple
from dataclasses import dataclass, replace
from pathlib import Path

import pytest
import torch
from torch import nn

from t3fast.errors import ConfigError, DivergenceError
from t3fast.io.checkpoint import load_checkpoint
from t3fast.training.graphed_step import WARMUP, GraphedStep, layout, map_tensors, tensors_of
from t3fast.training.trainer import Trainer
from tests.training.test_trainer import ToyTask, toy_config

Pair = namedtuple("Pair", "a b")


@dataclass
class Nested:
    x: torch.Tensor
    pair: Pair
    extra: dict
    missing: torch.Tensor | None = None
    label: str = "kept"


def _nested() -> Nested:
    return Nested(torch.zeros(2), Pair(torch.ones(3), [torch.full((1,), 2.0), 7]), {"m": torch.arange(4)})


def test_tensors_of_and_map_tensors_keep_the_nesting() -> None:
    batch = _nested()
    assert [t.tolist() for t in tensors_of(batch)] == [[0.0, 0.0], [1.0, 1.0, 1.0], [2.0], [0, 1, 2, 3]]
    doubled = map_tensors(batch, lambda t: t * 2)
    assert isinstance(doubled, Nested) and isinstance(doubled.pair, Pair) and doubled.label == "kept"
    assert doubled.pair.b[1] == 7 and doubled.missing is None
    assert [t.tolist() for t in tensors_of(doubled)] == [[0.0, 0.0], [2.0, 2.0, 2.0], [4.0], [0, 2, 4, 6]]
    assert layout(doubled) == layout(batch)
    assert layout(replace(batch, label="other")) != layout(batch)  # a value the graph would hold as captured


class VariantToy(ToyTask):
    """The toy regression with tensors for its logged values and the step's host-side choice
    drawn by ``step_variant`` (which of ``variants`` loss scales the step uses); ``crash_at``: the
    step call that raises."""

    def __init__(self, variants: int = 1, crash_at: int | None = None) -> None:
        super().__init__(stochastic=False)
        self.variants, self.crash_at = variants, crash_at
        self.drawn: list[int] = []
        self._next: int | None = None

    def step_variant(self) -> int:
        self._next = len(self.drawn) % self.variants
        self.drawn.append(self._next)
        return self._next

    def training_step(self, model: nn.Module, batch: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, dict]:
        self.calls += 1
        if self.calls == self.crash_at:
            raise RuntimeError("crash")
        variant = self._next if self._next is not None else (self.calls - 1) % self.variants
        self._next = None
        x, y = batch
        loss = nn.functional.mse_loss(model(x), y) * (1.0 + variant)
        return loss, {"mse": loss.detach() / (1.0 + variant)}


def _train(task: ToyTask, out_dir: Path, **kw) -> Trainer:
    trainer = Trainer(task, toy_config(out_dir, eval_every=0, amp=False, **kw))
    trainer.fit()
    return trainer


def _weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.module.state_dict().items()}


@pytest.mark.parametrize("variants", [1, 2])
def test_graphed_training_follows_eager_training(tmp_path: Path, variants: int, device: str) -> None:
    steps = 2 * (WARMUP + 3) * variants
    eager = _train(VariantToy(variants), tmp_path / "eager", steps=steps, device=device)
    task = VariantToy(variants)
    graphed = _train(task, tmp_path / "graphed", steps=steps, cuda_graph=True, device=device)
    assert eager.graphed is None and graphed.graphed is not None
    # each variant: WARMUP eager steps, then a capture; the rest replayed
    assert graphed.graphed.report() == {"graphs": variants, "replays": steps - WARMUP * variants,
                                        "eager_steps": WARMUP * variants, "failures": {}}
    assert task.drawn == [i % variants for i in range(steps)]
    # the same training: fused AdamW against the per-tensor loop, the same schedule and clipping
    for name, value in _weights(eager).items():
        torch.testing.assert_close(_weights(graphed)[name], value, rtol=1e-5, atol=1e-6)
    logs = [json.loads(line) for line in (tmp_path / "graphed" / "metrics.jsonl").read_text().splitlines()]
    eager_logs = [json.loads(line) for line in (tmp_path / "eager" / "metrics.jsonl").read_text().splitlines()]
    train = [e["values"] for e in logs if e["event"] == "train"]
    eager_train = [e["values"] for e in eager_logs if e["event"] == "train"]
    assert [v["lr"] for v in train] == pytest.approx([v["lr"] for v in eager_train])
    assert [v["mse"] for v in train] == pytest.approx([v["mse"] for v in eager_train], rel=1e-4)
    assert all(v["grad_norm"] > 0 for v in train)


def test_a_batch_of_another_shape_runs_eagerly() -> None:
    calls = []

    def body(batch: tuple[torch.Tensor, torch.Tensor]) -> dict[str, torch.Tensor]:
        calls.append(batch[0].shape[0])
        return {"sum": batch[0].sum() + batch[1].sum()}

    step = GraphedStep(body, torch.device("cpu"))
    full = [(torch.full((4, 2), float(i)), torch.ones(4)) for i in range(WARMUP + 3)]
    sums = [float(step(b)["sum"]) for b in full]
    assert sums == [8.0 * i + 4.0 for i in range(WARMUP + 3)]  # replays read the batch copied in
    short = (torch.ones(3, 2), torch.ones(3))
    assert float(step(short)["sum"]) == 9.0
    assert step.report() == {"graphs": 1, "replays": 3, "eager_steps": WARMUP + 1, "failures": {}}


def test_a_step_with_a_nan_loss_changes_no_weight_and_stops_the_run(tmp_path: Path, device: str) -> None:
    task = VariantToy()
    trainer = Trainer(task, toy_config(tmp_path, eval_every=0, steps=12, ckpt_every=0, cuda_graph=True, device=device))
    nan_at = WARMUP + 2  # a replayed step: a target in its batch is NaN
    batch = list(iter(trainer.sampler))[nan_at - 1]
    task.y[batch[0]] = float("nan")
    after: list[dict[str, torch.Tensor]] = []
    check = trainer._check_weights

    def spy(loss: float) -> None:  # the weights after each step that passed
        after.append({k: v.detach().clone() for k, v in trainer.module.state_dict().items()})
        check(loss)

    trainer._check_weights = spy
    with pytest.raises(DivergenceError, match=f"train step {nan_at}: the loss is not finite"):
        trainer.fit()
    assert trainer.graphed.replays == nan_at - WARMUP and len(after) == nan_at - 1
    for name, value in after[-1].items():  # the weights of the last good step
        assert torch.equal(trainer.module.state_dict()[name], value), name


def test_a_graphed_run_resumes_eagerly_and_back(tmp_path: Path) -> None:
    straight = _train(VariantToy(), tmp_path / "straight", steps=18, ckpt_every=6, cuda_graph=True)
    with pytest.raises(RuntimeError, match="crash"):  # stops after writing last.pt at step 6
        _train(VariantToy(crash_at=7), tmp_path / "a", steps=18, ckpt_every=6, cuda_graph=True)
    saved = load_checkpoint(tmp_path / "a" / "last.pt")
    group = saved["optimizer"]["param_groups"][0]
    assert isinstance(group["lr"], float) and group["fused"] is None and not group["capturable"]
    assert all(s["step"].device.type == "cpu" for s in saved["optimizer"]["state"].values())
    with pytest.raises(RuntimeError, match="crash"):  # eagerly, from the graphed run's optimiser state
        _train(VariantToy(crash_at=7), tmp_path / "a", steps=18, ckpt_every=6, resume=True)
    back = Trainer(VariantToy(), toy_config(tmp_path / "a", eval_every=0, steps=18, ckpt_every=6, resume=True,
                                            cuda_graph=True))
    assert back.step == 12 and back.scheduler.last_epoch == 12
    assert all(g["fused"] and isinstance(g["lr"], torch.Tensor) for g in back.optimizer.param_groups)
    back.fit()
    assert back.graphed.eager_steps == WARMUP
    for name, value in _weights(straight).items():
        torch.testing.assert_close(_weights(back)[name], value, rtol=1e-5, atol=1e-6)


def test_graphed_profile_starts_after_the_capture(tmp_path: Path) -> None:
    _train(VariantToy(), tmp_path, steps=WARMUP + 6, profile_steps=2, cuda_graph=True)
    profile = json.loads((tmp_path / "profile.json").read_text())
    assert set(profile["phases"]) == {"data", "step"} and profile["steps"] == 2


def test_cuda_graph_needs_a_task_that_names_its_host_choices(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="ToyTask has no step_variant"):
        Trainer(ToyTask(), toy_config(tmp_path, cuda_graph=True))
