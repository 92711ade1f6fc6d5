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


def output_path(root: str | Path, *parts: str) -> Path:
    """``root / parts`` as a file or folder to write: it must resolve inside ``root`` and no
    component below ``root`` may be a symbolic link (one left in an output folder would
    redirect the write anywhere). Raises :class:`~t3fast.errors.UsageError`."""
    root = Path(root)
    path = root
    for part in parts:
        path = path / part
        if path.is_symlink():
            raise UsageError(f"{path} is a symbolic link: not writing through it (remove it or choose another --out)")
    if not path.resolve().is_relative_to(root.resolve()):
        raise UsageError(f"{path} would lie outside {root}")
    return path


def output_dir(path: str | Path) -> Path:
    """``path`` as an output folder: absent (it will be created) or a folder, never a file.

    Checked before a command does any work, so a typo does not cost a model run.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {path} is a file, not a folder")
    _check_nearest_parent(path)
    return path


def output_file(path: str | Path, kind: str = "file") -> Path:
    """``path`` as an output file (``--out``, naming the ``kind`` written): not a folder, and
    the nearest existing folder above it really a folder. Checked before a command does any work."""
    path = Path(path)
    if path.is_dir():
        raise UsageError(f"--out {path} is a folder; it names the {kind} to write")
    _check_nearest_parent(path)
    return path


def _check_nearest_parent(path: Path) -> None:
    """The nearest existing folder above ``path`` must be a folder, not a file."""
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise UsageError(f"--out {path}: {parent} is a file, not a folder")
            break
