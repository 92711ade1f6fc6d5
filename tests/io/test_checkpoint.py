"""Atomic checkpoint writes: no temporary files left, an interrupted write keeps the old file."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest
import torch

import t3fast.io.checkpoint as ckpt
from t3fast.io.checkpoint import load_checkpoint, save_checkpoint


def test_round_trip_leaves_only_the_checkpoint(tmp_path: Path) -> None:
    state = {"model": {"w": torch.arange(6.0).reshape(2, 3)}, "step": 3, "best_score": float("-inf")}
    path = tmp_path / "sub" / "last.pt"
    save_checkpoint(state, path)
    save_checkpoint({**state, "step": 4}, path)  # overwrite in place
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]
    loaded = load_checkpoint(path)
    assert loaded["step"] == 4 and torch.equal(loaded["model"]["w"], state["model"]["w"])


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_failed_write_keeps_the_old_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, error: BaseException
) -> None:
    path = tmp_path / "last.pt"
    save_checkpoint({"step": 1}, path)

    def failing_save(obj: object, f) -> None:
        f.write(b"half a checkpoint")
        raise error

    monkeypatch.setattr(ckpt.torch, "save", failing_save)
    with pytest.raises(type(error)):
        save_checkpoint({"step": 2}, path)
    monkeypatch.undo()
    assert load_checkpoint(path)["step"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["last.pt"]


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_new_checkpoints_respect_the_umask(tmp_path: Path, umask: int, mode: int) -> None:
    old = os.umask(umask)
    try:
        assert ckpt.current_umask() == umask
        save_checkpoint({"step": 1}, tmp_path / "last.pt")
        with open(tmp_path / "plain", "wb") as f:  # what torch.save(path) would get
            f.write(b"")
    finally:
        os.umask(old)
    written = {name: stat.S_IMODE((tmp_path / name).stat().st_mode) for name in ("last.pt", "plain")}
    assert written == {"last.pt": mode, "plain": mode}


def test_a_replaced_checkpoint_keeps_its_permissions(tmp_path: Path) -> None:
    path = tmp_path / "best.pt"
    save_checkpoint({"step": 1}, path)
    path.chmod(0o640)
    save_checkpoint({"step": 2}, path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o640 and load_checkpoint(path)["step"] == 2


def test_weights_that_are_not_tensors_are_refused_on_reading(tmp_path: Path) -> None:
    """Every reader (loading a model, ``t3fast export``) may rely on tensors named by strings."""
    from t3fast.errors import CheckpointError
    from t3fast.io.checkpoint import AUTOENCODER, export_weights, read_checkpoint

    config = {"task": {"model": {}, "decoder_backend": "fused"}}
    path = tmp_path / "ae.pt"
    save_checkpoint({"model": {"encoder.w": torch.zeros(2), "decoder.w": "oops"}, "config": config}, path)
    with pytest.raises(CheckpointError, match=r"ae.pt: weight 'decoder.w' is a str, not a tensor"):
        read_checkpoint(path, AUTOENCODER)
    with pytest.raises(CheckpointError, match=r"weight 'decoder.w' is a str, not a tensor"):
        export_weights(path, tmp_path / "out.pt")
    assert not (tmp_path / "out.pt").exists()
    save_checkpoint({"model": {3: torch.zeros(2)}, "config": config}, path)
    with pytest.raises(CheckpointError, match=r"ae.pt: weights are named by strings, not by int 3"):
        read_checkpoint(path, AUTOENCODER)
