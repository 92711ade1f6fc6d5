"""Atomic checkpoint files: a crash or Ctrl-C mid-write never leaves a truncated checkpoint."""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from t3fast.errors import CheckpointError

#: checkpoint kinds, named after the command that writes them
AUTOENCODER = "stage-1 autoencoder checkpoint (from `t3fast train-ae`)"
WORLD_MODEL = "stage-2 world model checkpoint (from `t3fast train-wm`)"


def save_checkpoint(state: dict[str, Any], path: str | Path) -> None:
    """Write ``state`` with ``torch.save`` so that ``path`` holds either the old or the new file.

    The data goes to a temporary file in the same directory (``os.replace`` is atomic only
    within one file system), is flushed and fsynced, then renamed over ``path``. The file gets
    the permissions ``torch.save`` would give it: those of the file it replaces, else
    ``0o666`` less the umask (``mkstemp`` alone would make it private to its owner).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = file_mode(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:  # also KeyboardInterrupt: never leave the temporary file behind
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def file_mode(path: str | Path) -> int:
    """The permission bits a plain ``open(path, "w")`` would leave ``path`` with: those of the
    file already there, else ``0o666`` less the umask. For writers that go through ``mkstemp``."""
    try:
        st = os.stat(path)
        if stat.S_ISREG(st.st_mode):
            return stat.S_IMODE(st.st_mode)
    except OSError:
        pass
    return 0o666 & ~current_umask()


def current_umask() -> int:
    """The process umask. Read from ``/proc`` where there is one: setting it to read it back
    (``os.umask``) would change it for every thread for a moment."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o077)  # the strictest value while it is swapped out
    os.umask(mask)
    return mask


def load_checkpoint(path: str | Path, map_location: str | torch.device | None = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Loads with ``weights_only=True`` (no arbitrary code from the file): checkpoints hold only
    tensors, numbers, strings and containers of them.
    """
    return torch.load(path, map_location=map_location, weights_only=True)


def checkpoint_kind(state: Any) -> str | None:
    """:data:`AUTOENCODER`, :data:`WORLD_MODEL`, or None for anything else (e.g. a plain state_dict)."""
    if not (isinstance(state, dict) and isinstance(state.get("model"), dict) and isinstance(state.get("config"), dict)):
        return None
    task = state["config"].get("task")
    if not isinstance(task, dict):
        return None
    if "autoencoder_ckpt" in task:  # only stage 2 points at a stage-1 checkpoint
        return WORLD_MODEL
    if "decoder_backend" in task:
        return AUTOENCODER
    return None


def read_checkpoint(path: str | Path, kind: str | tuple[str, ...]) -> dict[str, Any]:
    """:func:`load_checkpoint` for a command that needs a checkpoint of ``kind`` (or of one of
    several kinds).

    Raises :class:`~t3fast.errors.CheckpointError` saying what the file is when it is missing,
    unreadable, not a t3fast checkpoint, a checkpoint of the other stage, or holds a weight that
    is not a tensor (whether the weights fit the config is checked where a model is built,
    :mod:`t3fast.pretrained`).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    try:
        state = load_checkpoint(path)
    except Exception as exc:  # torch.load fails in many ways on a file that is not a checkpoint
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {reason})") from exc
    kinds = (kind,) if isinstance(kind, str) else kind
    wanted = " or a ".join(kinds)
    found = checkpoint_kind(state)
    if found is None:
        raise CheckpointError(
            f"{path}: not a t3fast checkpoint (no model weights with their config; a plain state_dict "
            f"cannot be used); this command needs a {wanted}"
        )
    if found not in kinds:
        raise CheckpointError(f"{path}: this is a {found}; this command needs a {wanted}")
    for key, value in state["model"].items():  # what every reader of the weights relies on
        if not isinstance(key, str):
            raise CheckpointError(f"{path}: weights are named by strings, not by {type(key).__name__} {key!r}")
        if not isinstance(value, torch.Tensor):
            raise CheckpointError(f"{path}: weight {key!r} is a {type(value).__name__}, not a tensor")
    return state


def export_weights(src: str | Path, dst: str | Path, dtype: torch.dtype = torch.float16,
                   edit_config: Callable[[dict[str, Any], str | None], dict[str, Any]] | None = None) -> int:
    """Keep only what inference needs from a training checkpoint (model weights in ``dtype``,
    config, step), e.g. to ship it; returns the file size in bytes. Loading casts back to the
    model's dtype. ``src`` must be a stage-1 or stage-2 checkpoint (:func:`read_checkpoint`
    says what it is otherwise), read once. ``edit_config(config, kind)``: the config to store
    instead of the run's (``kind``: :func:`checkpoint_kind`), e.g. an inference setting."""
    state = read_checkpoint(src, (AUTOENCODER, WORLD_MODEL))
    weights = {k: v.to(dtype) if v.is_floating_point() else v for k, v in state["model"].items()}
    config = state.get("config", {})
    if edit_config is not None:
        config = edit_config(config, checkpoint_kind(state))
    save_checkpoint({"model": weights, "config": config, "step": state.get("step")}, dst)
    return Path(dst).stat().st_size


def _fsync_dir(directory: Path) -> None:
    """Make the rename itself durable; not every platform can open a directory."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
