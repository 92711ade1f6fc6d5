"""Stage 1 end to end through the command line: train-ae, resume, eval-ae."""

from __future__ import annotations

import json

import torch

from t3fast.commands.main import main
from t3fast.data.classes import DRIVEABLE_SURFACE, FREE, PEDESTRIAN
from t3fast.io.checkpoint import load_checkpoint
from t3fast.presets import preset
from t3fast.training.autoencoder.task import AutoencoderTask

TINY_RUN = [
    "data.train_scenes=1",
    "data.frames_per_scene=11",
    "data.val_scenes=1",
    "data.val_stride=4",
    "loss.num_occupied=2000",
    "loss.num_near_free=1000",
    "loss.num_far_free=500",
    "train.log_every=1",
    "train.eval_every=2",
    "train.ckpt_every=1",
]


def test_train_resume_and_evaluate(tmp_path, capsys):
    out = tmp_path / "run"
    args = ["train-ae", "--config", "small", "train.steps=2", f"train.out_dir={out}", *TINY_RUN]
    assert main(args) == 0
    assert {"last.pt", "best.pt", "metrics.jsonl", "config.yaml"} <= {p.name for p in out.iterdir()}
    assert load_checkpoint(out / "last.pt")["step"] == 2

    # a longer run resumes from step 2 instead of starting over
    assert main(["train-ae", "--config", "small", "--resume", "train.steps=3", f"train.out_dir={out}", *TINY_RUN]) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 3
    events = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert [e["step"] for e in events if e["event"] == "train"] == [1, 2, 3]  # each step logged once

    capsys.readouterr()
    result = tmp_path / "eval.json"
    assert main(["eval-ae", str(out / "last.pt"), "--split", "test", "--scenes", "1", "--out", str(result)]) == 0
    table = capsys.readouterr().out
    assert "| driveable_surface |" in table and "mIoU" in table
    summary = json.loads(result.read_text())
    assert 0 <= summary["iou"] <= 100 and summary["latent_size"] == 105_600 and summary["frames"] == 11


def test_class_weights_favour_rare_classes():
    cfg = preset("ae-small")
    cfg.data.train_scenes, cfg.data.frames_per_scene = 1, 11
    cfg.loss.class_weights, cfg.loss.class_weight_frames = True, 2
    weights = AutoencoderTask(cfg)._weights(torch.device("cpu"))
    assert weights.shape == (18,)
    assert weights.argmin() == FREE  # the most frequent class weighs least
    assert weights[DRIVEABLE_SURFACE] < weights[PEDESTRIAN]
