"""A training run's output folder: never replace a finished run by accident.

A new run needs an empty (or absent) ``out_dir``. A folder that already holds files is
continued with ``resume`` (its ``last.pt`` must exist) or ``resume_from`` a checkpoint inside
it, or replaced with ``overwrite``, which deletes the files the trainer writes and nothing else.

``overwrite`` deletes the old run only once the new one has proved it can run: after set-up
(model, optimiser, data) the old files move into ``out_dir/.replaced-run`` (:func:`set_aside`),
they come back if the new run fails before its first checkpoint (:func:`restore`), and they
are deleted when that checkpoint is written (:func:`drop_replaced`). A process killed in between
leaves them in ``.replaced-run``; the next ``overwrite`` of the folder sorts that out.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from t3fast.errors import UsageError

#: what a run writes into its out_dir (``overwrite`` deletes exactly these)
RUN_FILES = ("last.pt", "best.pt", "metrics.jsonl", "config.yaml")
RUN_DIRS = ("tb",)
#: the checkpoints among RUN_FILES: a run that wrote one of them has started
CHECKPOINTS = ("last.pt", "best.pt")
#: where ``overwrite`` keeps the replaced run until the new one writes its first checkpoint
REPLACED = ".replaced-run"


def check_out_dir(out_dir: str | Path, resume: bool, resume_from: str | None, overwrite: bool) -> None:
    """Raise :class:`~t3fast.errors.UsageError` unless a run may write into ``out_dir`` as asked."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"out_dir {out} is a file, not a folder")
    if resume and overwrite:
        raise UsageError("--resume continues the run in out_dir and --overwrite replaces it: pass one")
    if resume and not resume_from and not (out / "last.pt").is_file():
        raise UsageError(f"nothing to resume: {out / 'last.pt'} does not exist (drop --resume to start a new run)")
    if overwrite or resume or not out.is_dir():
        return
    if resume_from and Path(resume_from).resolve().parent == out.resolve():
        return  # continuing this folder's own run
    entries = sorted(p.name for p in out.iterdir())
    if entries:
        shown = ", ".join(entries[:5]) + (", ..." if len(entries) > 5 else "")
        raise UsageError(
            f"out_dir {out} is not empty ({shown}): continue its run with --resume (train.resume=true) "
            "or replace it with --overwrite (train.overwrite=true)"
        )


def clear_run(out_dir: str | Path) -> None:
    """Delete the files a run wrote into ``out_dir`` (and nothing else)."""
    out = Path(out_dir)
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
    for name in RUN_DIRS:
        if (out / name).is_symlink():
            (out / name).unlink()
        else:
            shutil.rmtree(out / name, ignore_errors=True)


def set_aside(out_dir: str | Path) -> bool:
    """Move the run in ``out_dir`` into ``out_dir/.replaced-run`` (``overwrite``, once the new
    run is set up); True when there is a replaced run to :func:`restore` or :func:`drop_replaced`.

    A ``.replaced-run`` left by an earlier ``overwrite`` that was killed is kept when the run
    beside it never wrote a checkpoint (that run's files are deleted), and deleted otherwise.
    """
    out, kept = Path(out_dir), Path(out_dir) / REPLACED
    if kept.is_dir() and not kept.is_symlink():
        if any((out / name).is_file() for name in CHECKPOINTS):
            shutil.rmtree(kept)  # the run beside it had started: it replaced the kept one
        else:
            clear_run(out)  # a run that never reached its first checkpoint
            return True
    present = [name for name in RUN_FILES + RUN_DIRS if os.path.lexists(out / name)]
    if not present:
        return False
    kept.mkdir()
    for name in present:
        os.replace(out / name, kept / name)
    return True


def restore(out_dir: str | Path) -> None:
    """Undo :func:`set_aside`: delete what the new run wrote and put the replaced run back."""
    out, kept = Path(out_dir), Path(out_dir) / REPLACED
    if not kept.is_dir():
        return
    clear_run(out)
    for path in kept.iterdir():
        os.replace(path, out / path.name)
    kept.rmdir()


def drop_replaced(out_dir: str | Path) -> None:
    """Delete the run :func:`set_aside` kept: the new run has written its first checkpoint."""
    shutil.rmtree(Path(out_dir) / REPLACED, ignore_errors=True)
