"""A training run's output folder: never replace a finished run by accident.

A new run needs an empty (or absent) ``out_dir``. A folder that already holds files is
continued with ``resume`` (its ``last.pt`` must exist) or ``resume_from`` a checkpoint inside
it, or replaced with ``overwrite``, which deletes the files the trainer writes and nothing else.

``overwrite`` deletes the old run only once the new one has proved it can run: after set-up
(model, optimiser, data) the old files move into ``out_dir/.replaced-run`` (:func:`set_aside`),
they come back if the new run fails before it has trained a step and written a checkpoint
(:func:`restore`; the ``best.pt`` of ``eval_at_start`` is the untrained model and does not count),
and they are deleted when it has (:func:`drop_replaced`). A process killed in between leaves
them in ``.replaced-run``; the next ``overwrite`` of the folder sorts that out, and ``resume``
says where they are.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from t3fast.errors import UsageError
from t3fast.io.checkpoint import load_checkpoint

#: what a run writes into its out_dir (``overwrite`` deletes exactly these)
RUN_FILES = ("last.pt", "best.pt", "metrics.jsonl", "config.yaml")
RUN_DIRS = ("tb",)
#: where ``overwrite`` keeps the replaced run until the new one has trained and written a checkpoint
REPLACED = ".replaced-run"


def check_out_dir(out_dir: str | Path, resume: bool, resume_from: str | None, overwrite: bool) -> None:
    """Raise :class:`~t3fast.errors.UsageError` unless a run may write into ``out_dir`` as asked."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"out_dir {out} is a file, not a folder")
    if resume and overwrite:
        raise UsageError("--resume continues the run in out_dir and --overwrite replaces it: pass one")
    if resume and not resume_from and not (out / "last.pt").is_file():
        raise UsageError(f"nothing to resume: {out / 'last.pt'} does not exist {_resume_advice(out)}")
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


def _resume_advice(out: Path) -> str:
    """What to do instead of resuming ``out``, which has no last.pt."""
    kept = out / REPLACED
    if kept.is_dir():
        return (f"but {kept} holds the run an interrupted --overwrite was replacing: move its files back into "
                f"{out} (over those there) to resume that run, or pass --overwrite instead of --resume to start anew")
    return "(drop --resume to start a new run)"


def has_trained(out_dir: str | Path) -> bool:
    """Whether the run in ``out_dir`` wrote a checkpoint after a training step: a ``last.pt``
    (written only after steps) or a ``best.pt`` of a step > 0. An unreadable ``best.pt`` counts
    as untrained, so that the run it would replace is kept."""
    out = Path(out_dir)
    if (out / "last.pt").is_file():
        return True
    if not (out / "best.pt").is_file():
        return False
    try:
        step = load_checkpoint(out / "best.pt")["step"]
    except Exception:  # cut short or not a checkpoint: not proof that the run trained
        return False
    return isinstance(step, int) and step > 0


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
    beside it never trained (:func:`has_trained`; that run's files are deleted), and deleted otherwise.
    """
    out, kept = Path(out_dir), Path(out_dir) / REPLACED
    if kept.is_dir() and not kept.is_symlink():
        if has_trained(out):
            shutil.rmtree(kept)  # the run beside it had trained: it replaced the kept one
        else:
            clear_run(out)  # a run killed before it trained a step and saved it
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
    """Delete the run :func:`set_aside` kept: the new run has trained and written a checkpoint."""
    shutil.rmtree(Path(out_dir) / REPLACED, ignore_errors=True)
