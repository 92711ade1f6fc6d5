"""Device mix-ups in the training steps, caught without a GPU: each training command runs with
its steps (loss and backward) under the default device "meta" while the model and the batch are
on the CPU. A tensor a step makes without its inputs' device lands on meta, and the first op
that mixes it with them fails, as a CPU tensor beside CUDA ones does on a GPU; one made from
host data on purpose would be a copy to the device in every step there. The losses logged must
be those of a plain run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from t3fast.commands.main import main
from t3fast.training.trainer import Trainer

from .tiny_runs import TINY_AE, TINY_BOX, TINY_MOTION, TINY_PLAN, TINY_WM


def _commands(world: Path, cache: Path) -> dict[str, list[str]]:
    ae = str(world.parent.parent / "ae" / "last.pt")
    wm = ["train-wm", "--config", "small", "--ae", ae, f"data.cache_dir={cache / 'wm'}", *TINY_WM]
    return {
        "train-ae": ["train-ae", "--config", "small", *TINY_AE],
        "train-wm": wm,
        "train-wm graphed": [*wm, "train.cuda_graph=true"],  # the whole step a CUDA graph holds
        # the paper preset's path: labelled windows from the aligned cache, 6-step rollouts
        "train-wm labels": ["train-wm", "--config", "small-delta", "--ae", ae, f"data.cache_dir={cache / 'labels'}",
                            "data.cache_labels=true", "loss.rollout_steps=6", *TINY_WM],
        "train-planner": ["train-planner", "--wm", str(world), f"data.cache_dir={cache / 'plan'}", *TINY_PLAN],
        "train-motion": ["train-motion", "--wm", str(world), f"data.cache_dir={cache / 'motion'}", *TINY_MOTION],
        "train-box-motion": ["train-box-motion", "--wm", str(world), f"data.cache_dir={cache / 'box'}", *TINY_BOX],
    }


def _losses(out: Path) -> list[dict[str, float]]:
    events = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in e["values"].items() if k != "samples_per_s"} for e in events if e["event"] == "train"]


@pytest.fixture
def steps_on_meta(monkeypatch):
    """Every trainer made from here on runs its task's training steps under ``torch.device("meta")``."""
    made = Trainer.__init__

    def init(self, task, cfg):
        step = task.training_step

        def on_meta(model, batch):
            with torch.device("meta"):
                return step(model, batch)

        task.training_step = on_meta
        made(self, task, cfg)

    monkeypatch.setattr(Trainer, "__init__", init)


@pytest.mark.parametrize("name", ["train-ae", "train-wm", "train-wm graphed", "train-wm labels", "train-planner",
                                  "train-motion", "train-box-motion"])
def test_each_training_step_makes_its_tensors_on_the_models_device(name, world_ckpt, tmp_path, request):
    command = _commands(world_ckpt, tmp_path / "cache")[name]
    steps = ["train.steps=2", "train.log_every=1", "train.eval_every=0", "train.ckpt_every=0"]
    assert main([*command, *steps, f"train.out_dir={tmp_path / 'plain'}"]) == 0
    request.getfixturevalue("steps_on_meta")
    assert main([*command, *steps, f"train.out_dir={tmp_path / 'meta'}"]) == 0
    plain, meta = _losses(tmp_path / "plain"), _losses(tmp_path / "meta")
    assert len(plain) == 2 and meta == plain
