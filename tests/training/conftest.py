"""Fixtures shared by the training tests: a tiny trained world model, made once per session."""

from __future__ import annotations

import pytest

from t3fast.commands.main import main
from t3fast.io.checkpoint import load_checkpoint
from t3fast.pretrained import load_world_model

from .tiny_runs import TINY_AE, TINY_WM


@pytest.fixture(scope="session")
def world_ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("stage2")
    assert main(["train-ae", "--config", "small", "train.steps=1", f"train.out_dir={root / 'ae'}", *TINY_AE]) == 0
    out = root / "wm"
    args = ["train-wm", "--config", "small", "--ae", str(root / "ae" / "last.pt"), f"data.cache_dir={root / 'cache'}",
            f"train.out_dir={out}", *TINY_WM]
    assert main([*args, "train.steps=1"]) == 0
    assert main([*args, "train.steps=2", "--resume"]) == 0  # resumes from step 1
    assert load_checkpoint(out / "last.pt")["step"] == 2
    assert load_world_model(out / "last.pt").world_config.ego_aligned
    return out / "last.pt"
