"""The inference API: shipped names and checkpoint paths load the same model, without training code."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import t3fast
from t3fast.errors import CheckpointError
from t3fast.io.checkpoint import load_checkpoint
from t3fast.pretrained import SHIPPED_DIR, shipped_names


def test_names_resolve_to_the_shipped_checkpoints():
    assert "wm-small" in shipped_names()
    by_name = t3fast.load_world_model("wm-small")
    by_path = t3fast.load_world_model(SHIPPED_DIR / "wm-small.pt")
    assert not by_name.training
    for (k, a), b in zip(by_name.state_dict().items(), by_path.state_dict().values()):
        assert torch.equal(a, b), k
    assert by_name.world_config.ego_aligned and by_name.autoencoder_config.latent == "triplane"


def test_autoencoder_from_a_world_model_has_its_encoder_and_decoder():
    world = t3fast.load_world_model("wm-small")
    ae = t3fast.load_autoencoder("wm-small")
    for part in ("encoder", "decoder"):
        for (k, a), b in zip(getattr(ae, part).state_dict().items(), getattr(world, part).state_dict().values()):
            assert torch.equal(a, b), f"{part}.{k}"
    labels = torch.full((1, 200, 200, 16), 17, dtype=torch.uint8)
    labels[..., 0] = 11
    with torch.no_grad():
        assert ae.reconstruct(labels).shape == (1, 200, 200, 16)


def test_a_stage1_checkpoint_loads_as_autoencoder_not_as_world_model(tmp_path):
    from t3fast.io.checkpoint import save_checkpoint
    from t3fast.io.config import config_to_dict

    world = load_checkpoint(SHIPPED_DIR / "wm-small.pt")
    task = world["config"]["task"]
    stage1 = {"model": {k: v for k, v in world["model"].items() if k.split(".")[0] in ("encoder", "decoder")},
              "config": {"task": {"model": task["autoencoder"], "decoder_backend": "fused"}}, "step": 1}
    save_checkpoint(stage1, tmp_path / "ae.pt")
    assert config_to_dict(t3fast.load_autoencoder(tmp_path / "ae.pt").config) == task["autoencoder"]
    with pytest.raises(CheckpointError, match="stage-1 autoencoder checkpoint.*needs a stage-2"):
        t3fast.load_world_model(tmp_path / "ae.pt")


def test_an_unknown_name_lists_the_shipped_ones():
    with pytest.raises(CheckpointError, match="neither a checkpoint file nor a shipped model.*wm-small"):
        t3fast.load_world_model("wm-huge")


def test_inference_does_not_import_the_training_stack():
    code = ("import sys, t3fast; t3fast.load_world_model('wm-small'); "
            "print(sorted(m for m in sys.modules if m.startswith(('t3fast.training', 't3fast.evaluation'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
