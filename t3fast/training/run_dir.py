"""A training run's output folder: never replace a finished run by accident.

A new run needs an empty (or absent) ``out_dir``. A folder that already holds files is
continued with ``resume`` (its ``last.pt`` must exist) or ``resume_from`` a checkpoint inside
it, or replaced with ``overwrite``, which deletes the files the trainer writes and nothing else.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from t3fast.errors import UsageError

#: what a run writes into its out_dir (``overwrite`` deletes exactly these)
RUN_FILES = ("last.pt", "best.pt", "metrics.jsonl", "config.yaml")
RUN_DIRS = ("tb",)


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
    """Delete the files a previous run wrote into ``out_dir`` (for ``overwrite``)."""
    out = Path(out_dir)
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
    for name in RUN_DIRS:
        shutil.rmtree(out / name, ignore_errors=True)
