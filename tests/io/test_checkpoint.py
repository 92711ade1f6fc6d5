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
    from t3fast.io.checkpoint import AUTOENCODER, read_checkpoint
    from t3fast.pretrained import export_weights

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


# ---------------------------------------------------------------- weights that are not finite
def _stage1(tmp_path: Path, weight: torch.Tensor) -> Path:
    path = tmp_path / "ae.pt"
    config = {"task": {"model": {}, "decoder_backend": "fused"}}
    save_checkpoint({"model": {"encoder.w": torch.zeros(2), "decoder.w": weight}, "config": config}, path)
    return path


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_weights_that_are_not_finite_are_refused_on_reading(tmp_path: Path, bad: float) -> None:
    """A NaN weight would forecast silently wrong; the file and the weight are named."""
    from t3fast.errors import CheckpointError
    from t3fast.io.checkpoint import AUTOENCODER, read_checkpoint

    weight = torch.ones(4, 5, dtype=torch.float16)
    weight[1, 2] = weight[3, 0] = bad
    path = _stage1(tmp_path, weight)
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path, AUTOENCODER)
    assert str(info.value) == f"{path}: weight 'decoder.w' is not finite (2 of its 20 values are NaN or infinite)"


# ---------------------------------------------------------------- archives that would inflate
def _refused_without_torch_load(path: Path, monkeypatch: pytest.MonkeyPatch, reason: str) -> None:
    """``load_checkpoint(path)`` raises a one-line CheckpointError before torch.load sees the file."""
    from t3fast.errors import CheckpointError

    def no_load(*args: object, **kwargs: object) -> None:
        raise AssertionError("torch.load was called")

    monkeypatch.setattr(ckpt.torch, "load", no_load)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(path)
    assert str(info.value) == f"{path}: not a readable checkpoint ({reason})"


def _records(path: Path) -> list[tuple[str, bytes]]:
    import zipfile

    with zipfile.ZipFile(path) as archive:
        return [(info.filename, archive.read(info)) for info in archive.infolist()]


def test_a_deflated_record_is_refused_before_it_is_inflated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """torch.save stores records uncompressed; 64 MiB of zeros deflate to 64 KiB and would
    inflate inside torch.load (a 2.5 MB file made 1 GB of memory)."""
    import zipfile

    path = tmp_path / "bomb.pt"
    save_checkpoint({"model": {"w": torch.zeros(4)}}, path)
    records = _records(path)
    with zipfile.ZipFile(path, "w") as bomb:
        for name, content in records:
            if not name.endswith("/data/0"):
                bomb.writestr(name, content)
                continue
            info = zipfile.ZipInfo(name)
            info.compress_type = zipfile.ZIP_DEFLATED
            with bomb.open(info, "w", force_zip64=True) as record:
                for _ in range(64):
                    record.write(bytes(2**20))
    assert path.stat().st_size < 2**20
    data = next(name for name, _ in records if name.endswith("/data/0"))
    _refused_without_torch_load(path, monkeypatch, f"record {data!r} is deflated; torch.save stores its records "
                                                   "uncompressed")


def test_records_larger_than_the_file_are_refused_before_they_are_read(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stored record whose central directory entry declares 512 MiB: torch.load would allocate
    that much before finding the data missing."""
    import struct
    import zipfile

    path = tmp_path / "liar.pt"
    save_checkpoint({"model": {"w": torch.zeros(4)}}, path)
    data = next(name for name, _ in _records(path) if name.endswith("/data/0")).encode()
    raw = bytearray(path.read_bytes())
    entry = raw.index(b"PK\x01\x02")  # the central directory: 46 bytes, then the record's name
    while raw[entry + 46 : entry + 46 + len(data)] != data:
        entry = raw.index(b"PK\x01\x02", entry + 4)
    struct.pack_into("<I", raw, entry + 24, 512 * 2**20)  # its uncompressed size
    path.write_bytes(bytes(raw))
    with zipfile.ZipFile(path) as archive:
        declared = sum(info.file_size for info in archive.infolist())
    _refused_without_torch_load(path, monkeypatch, f"its records declare {declared:,} bytes, more than the "
                                                   f"file's {path.stat().st_size:,}")


def test_what_is_not_a_zip_archive_is_refused_before_torch_load(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """torch.save's legacy format sizes its storages from the pickle alone (a few bytes can ask for
    any amount of memory); every checkpoint t3fast writes is a zip archive."""
    path = tmp_path / "legacy.pt"
    torch.save({"model": {"w": torch.zeros(4)}}, path, _use_new_zipfile_serialization=False)
    _refused_without_torch_load(path, monkeypatch, "BadZipFile: File is not a zip file")


def test_a_special_file_is_not_replaced(tmp_path: Path) -> None:
    """Renaming over a FIFO (or, as root, a device) would replace the node itself."""
    from t3fast.errors import UsageError

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(UsageError, match=f"^{fifo} is a FIFO, not a regular file: not writing over it$"):
        save_checkpoint({"step": 1}, fifo)
    assert stat.S_ISFIFO(fifo.lstat().st_mode) and [p.name for p in tmp_path.iterdir()] == ["fifo"]
