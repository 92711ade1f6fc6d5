"""Checkpoint files: written atomically (a crash or Ctrl-C mid-write never leaves a truncated
checkpoint) and read only once their archive is known not to inflate beyond the file."""

from __future__ import annotations

import os
import stat
import tempfile
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

import torch

from t3fast.errors import CheckpointError, UsageError

#: checkpoint kinds, named after the command that writes them
AUTOENCODER = "stage-1 autoencoder checkpoint (from `t3fast train-ae`)"
WORLD_MODEL = "stage-2 world model checkpoint (from `t3fast train-wm`)"


def save_checkpoint(state: dict[str, Any], path: str | Path,
                    check: Callable[[Path], None] | None = None) -> None:
    """Write ``state`` with ``torch.save`` so that ``path`` holds either the old or the new file.

    The data goes to a temporary file in the same directory (``os.replace`` is atomic only
    within one file system), is flushed and fsynced, then renamed over ``path``. The file gets
    the permissions ``torch.save`` would give it: those of the file it replaces, else
    ``0o666`` less the umask (``mkstemp`` alone would make it private to its owner).
    ``check(written)``, if given, runs on the complete temporary file before the rename; what
    it raises leaves ``path`` as it was. Something at ``path`` that is not a regular file (a
    FIFO, a device) is refused (:func:`check_replaceable`).
    """
    path = Path(path)
    check_replaceable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = file_mode(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        if check is not None:
            check(Path(tmp))
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:  # also KeyboardInterrupt: never leave the temporary file behind
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def check_replaceable(path: str | Path) -> None:
    """Raises :class:`~t3fast.errors.UsageError` when ``path`` exists and is neither a regular
    file nor a symbolic link: renaming over a FIFO or a device (``/dev/null`` as root) would
    replace the node itself, and writing into one would block or reach the device."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not (stat.S_ISREG(mode) or stat.S_ISLNK(mode)):
        raise UsageError(f"{path} is a {_file_type(mode)}, not a regular file: not writing over it")


def _file_type(mode: int) -> str:
    """What ``mode`` (``st_mode``) says a file is, in words."""
    types = ((stat.S_ISDIR, "folder"), (stat.S_ISCHR, "character device"), (stat.S_ISBLK, "block device"),
             (stat.S_ISFIFO, "FIFO"), (stat.S_ISSOCK, "socket"))
    return next((name for test, name in types if test(mode)), "special file")


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
    tensors, numbers, strings and containers of them. The archive is checked first
    (:func:`check_archive`), from the same open file that ``torch.load`` then reads.
    """
    with open(path, "rb") as f:
        check_archive(f, path)
        f.seek(0)
        return torch.load(f, map_location=map_location, weights_only=True)


def check_archive(f: IO[bytes], path: str | Path) -> None:
    """Raises :class:`~t3fast.errors.CheckpointError` unless ``f`` is a zip archive whose records
    are all stored uncompressed and together no larger than the file, as ``torch.save`` writes
    them. Only the archive's central directory is read: ``torch.load`` allocates each record at
    its declared size, so a deflated record or a false size would take memory out of all
    proportion to the file (a 2.5 MB file of deflated zeros made 1 GB) before any check of
    the contents could refuse it. The legacy, non-zip format is refused too: it sizes its
    storages from the pickle alone."""
    try:
        with zipfile.ZipFile(f) as archive:
            records = archive.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, EOFError) as exc:
        reason = (str(exc).strip().splitlines() or [""])[0]
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {reason})") from exc
    for record in records:
        if record.compress_type != zipfile.ZIP_STORED:
            method = "deflated" if record.compress_type == zipfile.ZIP_DEFLATED else "compressed"
            raise CheckpointError(f"{path}: not a readable checkpoint (record {record.filename!r} is {method}; "
                                  "torch.save stores its records uncompressed)")
    declared = sum(record.file_size for record in records)
    size = os.fstat(f.fileno()).st_size
    if declared > size:
        raise CheckpointError(f"{path}: not a readable checkpoint (its records declare {declared:,} bytes, more "
                              f"than the file's {size:,})")


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
    is not a tensor or not finite (whether the weights fit the config is checked where a model
    is built, :mod:`t3fast.pretrained`).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint not found")
    state = load_readable_checkpoint(path)
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
    check_finite(state["model"], path)
    return state


def check_finite(weights: Mapping[str, torch.Tensor], path: str | Path) -> None:
    """Raises :class:`~t3fast.errors.CheckpointError` naming the first floating-point weight
    that holds a NaN or an infinity: a model loaded with it would forecast wrong without a word."""
    key = first_nonfinite(weights)
    if key is not None:
        value = weights[key]
        bad = int((~torch.isfinite(value)).sum())
        raise CheckpointError(f"{path}: weight {key!r} is not finite ({bad} of its {value.numel()} values are "
                              "NaN or infinite)")


def first_nonfinite(tensors: Mapping[str, Any]) -> str | None:
    """The name of the first floating-point tensor in ``tensors`` holding a NaN or an infinity,
    else None. One host synchronisation for all of them (they must share a device)."""
    floats = {k: t for k, t in tensors.items() if isinstance(t, torch.Tensor) and t.is_floating_point()}
    if not floats:
        return None
    # a NaN or an infinity makes a tensor's norm one: a few multi-tensor kernels for all of them
    # (per tensor, two ops each: thousands of launches a training step on a GPU)
    norms = torch._foreach_norm([t.detach() for t in floats.values()])
    if bool(torch.stack([n.float() for n in norms]).isfinite().all()):
        return None
    finite = torch.stack([torch.isfinite(t).all() for t in floats.values()])
    if bool(finite.all()):
        return None
    return list(floats)[int((~finite).nonzero()[0, 0])]


def load_readable_checkpoint(path: str | Path) -> Any:
    """:func:`load_checkpoint`, with any failure to read ``path`` (cut short, not a zip, a
    payload torch refuses) as a one-line :class:`~t3fast.errors.CheckpointError` naming it."""
    try:
        return load_checkpoint(path)
    except CheckpointError:
        raise
    except Exception as exc:  # torch.load fails in many ways on a file that is not a checkpoint
        reason = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {reason})") from exc


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
