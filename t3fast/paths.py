"""Paths built from untrusted names: one folder level each, never outside their root."""

from __future__ import annotations

from pathlib import Path, PurePosixPath, PureWindowsPath

from t3fast.errors import DataFormatError, UsageError


def check_name(name: object, what: str) -> str:
    """Return ``name`` if it is safe as a single path component, else raise ``DataFormatError``.

    Scene names and tokens come from downloaded info files and become folder names; a
    separator, ``..`` or an absolute name would read or write outside the data or output folder.
    ``what`` says where the name came from, for the message.
    """
    if not isinstance(name, str):
        raise DataFormatError(f"{what} must be a string, got {type(name).__name__}")
    unsafe = (
        name in ("", ".", "..")
        or "\0" in name
        or len(PurePosixPath(name).parts) != 1
        or len(PureWindowsPath(name).parts) != 1
    )
    if unsafe:
        raise DataFormatError(f"{what} {name!r} is not a plain folder name (no separators, '..' or absolute paths)")
    return name


def inside(root: str | Path, *parts: str) -> Path:
    """``root / parts``, refusing a result that resolves (symbolic links included) outside ``root``."""
    root = Path(root)
    path = root.joinpath(*parts)
    if not path.resolve().is_relative_to(root.resolve()):
        raise DataFormatError(f"{path} would lie outside {root}")
    return path


def output_dir(path: str | Path) -> Path:
    """``path`` as an output folder: absent (it will be created) or a folder, never a file.

    Checked before a command does any work, so a typo does not cost a model run.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {path} is a file, not a folder")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise UsageError(f"--out {path}: {parent} is a file, not a folder")
            break
    return path
