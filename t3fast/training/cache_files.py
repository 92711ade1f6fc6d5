"""Training caches on disk: one file per entry (a scene's windows, or one window), each saying
what it holds, read back only when it holds what is asked for.

An entry file is ``{"identity": ..., "payload": ...}``: the identity names the cache (its kind
and its key: the settings and code the content depends on), the split, the scene (and the
window) and the shape of every payload tensor; the payload is a flat dict of tensors. The
reader checks the identity, that the payload holds exactly the cache's fields with their dtypes
and shapes (:class:`Field`), that its floating-point values are finite, and what the cache adds
(e.g. ids in range). A file that fails any of it (truncated, not a checkpoint, a pickle that
``weights_only`` refuses, another entry's file, a symbolic link, NaN values) is named in a
warning and built again, so a rerun works without deleting anything by hand. Reads never run
code from a file (``weights_only``); writes are atomic with a temporary file of their own
(:func:`~t3fast.io.checkpoint.save_checkpoint`), so an interrupted build keeps every entry it
finished and builders of the same cache never collide.
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import Dataset
from tqdm import tqdm

from t3fast.data.synthetic import SyntheticDriving, SyntheticScenes
from t3fast.errors import CheckpointError
from t3fast.io.checkpoint import load_checkpoint, save_checkpoint

log = logging.getLogger(__name__)

Dim = int | str | None  # a size, a name every use of which has one size within an entry, or any size


@dataclass(frozen=True)
class Field:
    """One payload tensor: its dtype and its shape, a :data:`Dim` per axis."""

    dtype: torch.dtype
    shape: tuple[Dim, ...]


Payload = dict[str, Tensor]
Layout = dict[str, Field]
#: a cache's own check of a payload that has its layout: what is wrong, or None
Check = Callable[[Payload], str | None]


class BrokenEntry(Exception):
    """A cache file that cannot be used; the message says why."""


def world_digest(scenes: SyntheticScenes) -> str:
    """Short hash of what the split's first scene holds (labels, poses, boxes): a change of the
    synthetic world that changes its data changes it; an edit that does not, does not."""
    scene = scenes.packed(0)
    h = hashlib.sha256()
    for part in (*scene.occ, scene.ego_poses.tobytes(), scene.boxes.tobytes(), scene.labels.tobytes()):
        h.update(part)
    return h.hexdigest()[:12]


def write_entry(path: Path, identity: dict[str, Any], payload: Payload) -> None:
    """Write ``payload`` to ``path`` atomically, with ``identity`` and its tensors' shapes."""
    shapes = {name: list(value.shape) for name, value in payload.items()}
    save_checkpoint({"identity": {**identity, "shapes": shapes}, "payload": payload}, path)


def read_entry(path: Path, identity: dict[str, Any], layout: Layout, check: Check | None = None) -> Payload:
    """The payload of the entry file ``path``; raises :class:`BrokenEntry` unless the file is a
    regular file holding the entry ``identity`` with the fields of ``layout``, finite, and
    ``check`` finds nothing wrong."""
    if path.is_symlink():
        raise BrokenEntry(f"a symbolic link to {path.readlink()}, not a file the cache wrote")
    try:
        state = load_checkpoint(path)
    except CheckpointError as exc:  # the archive itself is refused; the message starts with the path
        raise BrokenEntry(str(exc).removeprefix(f"{path}: ")) from exc
    except Exception as exc:  # torch.load fails in many ways on a file it did not write whole
        reason = (str(exc).strip().splitlines() or [""])[0]
        raise BrokenEntry(f"not a readable cache file ({type(exc).__name__}: {reason})") from exc
    if not (isinstance(state, dict) and isinstance(state.get("identity"), dict)
            and isinstance(state.get("payload"), dict)):
        raise BrokenEntry(f"not a cache file (a {type(state).__name__} without identity and payload)")
    stored, payload = state["identity"], state["payload"]
    if any(stored.get(k) != v for k, v in identity.items()):
        raise BrokenEntry(f"holds {describe(stored)}, not {describe(identity)}")
    _check_fields(payload, layout, stored.get("shapes"))
    reason = check(payload) if check is not None else None
    if reason:
        raise BrokenEntry(reason)
    return payload


def describe(identity: dict[str, Any]) -> str:
    """An identity in words: ``plan cache 3f2a..., train scene 4``."""
    where = " ".join(f"{k} {identity.get(k)}" for k in identity if k not in ("cache", "key", "shapes"))
    return f"{identity.get('cache')} cache {identity.get('key')}, {where}"


def _check_fields(payload: dict, layout: Layout, shapes: Any) -> None:
    """Exactly the fields of ``layout``, each a tensor of its dtype and shape (named sizes
    agreeing), the shape ``shapes`` recorded for it, and finite."""
    if set(payload) != set(layout):
        missing, extra = sorted(set(layout) - set(payload)), sorted(set(payload) - set(layout), key=str)
        raise BrokenEntry(f"fields {missing} missing, {extra} unexpected")
    sizes: dict[str, int] = {}
    for name, field in layout.items():
        value = payload[name]
        if not isinstance(value, Tensor):
            raise BrokenEntry(f"field {name!r} is a {type(value).__name__}, not a tensor")
        if value.dtype != field.dtype:
            raise BrokenEntry(f"field {name!r} is {value.dtype}, not {field.dtype}")
        if not (isinstance(shapes, dict) and shapes.get(name) == list(value.shape)) or not _fits(
                value.shape, field.shape, sizes):
            raise BrokenEntry(f"field {name!r} has shape {list(value.shape)}, not {_shape_words(field.shape)}")
        if value.is_floating_point() and not _all_finite(value):
            raise BrokenEntry(f"field {name!r} holds NaN or infinite values")


def _fits(shape: torch.Size, dims: tuple[Dim, ...], sizes: dict[str, int]) -> bool:
    """``shape`` matches ``dims``; named sizes are recorded in ``sizes`` on first use."""
    if len(shape) != len(dims):
        return False
    for size, dim in zip(shape, dims):
        if isinstance(dim, str):
            dim = sizes.setdefault(dim, size)
        if dim is not None and size != dim:
            return False
    return True


def _all_finite(value: Tensor) -> bool:
    """Whether every value is finite: a NaN or an infinity makes the float64 sum non-finite, and
    finite float16/float32 values cannot overflow it (a few times faster than ``isfinite``)."""
    return bool(torch.isfinite(value.sum(dtype=torch.float64)))


def _shape_words(dims: tuple[Dim, ...]) -> str:
    return "[" + ", ".join("*" if d is None else str(d) for d in dims) + "]"


def read_or_none(path: Path, identity: dict[str, Any], layout: Layout, check: Check | None = None) -> Payload | None:
    """:func:`read_entry`, or None when there is no file or, after a warning naming it, it is
    broken (it is to be built again)."""
    if not (path.exists() or path.is_symlink()):
        return None
    try:
        return read_entry(path, identity, layout, check)
    except BrokenEntry as exc:
        log.warning("%s: %s; building it again", path, exc)
        return None


class SceneFiles(Dataset):
    """The windows of a split cached as one entry file per scene in ``root``: which windows
    each scene holds, its file, which scenes are missing or broken, building them, and reading
    them all back. A subclass names its ``kind`` and gives a scene's :meth:`layout` and
    :meth:`build_scene` (and :meth:`check`).

    Args:
        windows: the windows of the split.
        root: the cache's folder.
        key: what the content depends on (also in ``root``'s name).
        scenes: the scenes cached here (default: all of ``windows``').
    """

    kind = ""
    desc = "cache scenes"  # the progress bar's

    def __init__(self, windows: SyntheticDriving, root: Path, key: str, scenes: Iterable[int] | None = None):
        self.windows, self.root, self.key = windows, root, key
        wanted = None if scenes is None else set(scenes)
        self._by_scene: dict[int, list[int]] = {}
        for index in range(len(windows)):
            scene = windows.locate(index)[0]
            if wanted is None or scene in wanted:
                self._by_scene.setdefault(scene, []).append(index)
        self._read: dict[int, Payload] = {}  # scenes read (and checked) or built, until read_scenes()

    def path(self, scene: int) -> Path:
        return self.root / f"scene{scene:05d}.pt"

    def identity(self, scene: int) -> dict[str, Any]:
        return {"cache": self.kind, "key": self.key, "split": self.windows.scenes.split, "scene": scene}

    def layout(self, scene: int) -> Layout:
        """The fields of ``scene``'s payload."""
        raise NotImplementedError

    def build_scene(self, scene: int) -> Payload:
        """``scene``'s payload, computed."""
        raise NotImplementedError

    def check(self, payload: Payload) -> str | None:
        """What is wrong with a payload that has its layout, beyond it (None: nothing)."""
        return None

    def windows_of(self, scene: int) -> int:
        return len(self._by_scene[scene])

    def missing(self) -> list[int]:
        """Scenes not in the cache, or whose file is broken (each named in a warning); the
        others are read."""
        todo = []
        for scene in self._by_scene:
            if scene not in self._read:
                payload = read_or_none(self.path(scene), self.identity(scene), self.layout(scene), self.check)
                if payload is None:
                    todo.append(scene)
                else:
                    self._read[scene] = payload
        return todo

    def scene_windows(self, scene: int) -> list:
        """The windows (samples) of ``scene``, in order."""
        return [self.windows[i] for i in self._by_scene[scene]]

    @torch.no_grad()
    def build(self, progress: bool = True) -> int:
        """Build every scene that is missing or broken; returns how many were built."""
        todo = self.missing()
        for scene in tqdm(todo, desc=self.desc, unit="scene", disable=not progress or not todo):
            payload = self.build_scene(scene)
            write_entry(self.path(scene), self.identity(scene), payload)
            self._read[scene] = payload
        return len(todo)

    def read_scenes(self) -> list[Payload]:
        """Every scene's payload, in scene order; refuses a cache that misses some."""
        missing = self.missing()
        if missing:
            raise FileNotFoundError(f"{self.root}: {len(missing)} scenes are not cached yet (build() first)")
        parts = [self._read[s] for s in sorted(self._by_scene)]
        self._read = {}  # the caller keeps them
        return parts

    def __len__(self) -> int:
        return sum(len(indices) for indices in self._by_scene.values())
