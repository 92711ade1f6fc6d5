"""Compact text encoding of label volumes and visibility masks, for embedding in HTML.

A pack holds ``T`` volumes ``[X, Y, Z]`` (Occ3D: ``[200, 200, 16]``). Each volume is
flattened with z slowest, then x, then y fastest (``vol.transpose(2, 0, 1).ravel()``), so
the ground layer and the free upper layers become long runs, and run-length encoded.
The byte layout, zlib-compressed and then base64-encoded (browsers inflate it with
``DecompressionStream("deflate")``), is, little-endian::

    header   "T3VX", version u8 (1), kind u8 (0 labels, 1 mask), T u32, X u16, Y u16, Z u16
    runs     T x u32: the number of runs of each volume
    values   one u8 per run, every volume's runs in order
    lengths  one unsigned LEB128 varint per run, in the same order

Labels must be Occ3D ids (0..17, or 255 for ignore); masks are bool and pack as 0/1.
``unpack_frames(pack_frames(x))`` returns ``x`` exactly.
"""

from __future__ import annotations

import base64
import binascii
import struct
import zlib

import numpy as np

from t3fast.data import classes as C
from t3fast.errors import DataFormatError

MAGIC = b"T3VX"
VERSION = 1
LABELS, MASK = 0, 1
_HEADER = struct.Struct("<4sBBIHHH")


def _check_volumes(frames: object, name: str, dtype: type) -> np.ndarray:
    """``frames`` as an array ``[T, *GRID_SHAPE]`` of ``dtype``, or a DataFormatError naming ``name``."""
    arr = np.asarray(frames)
    expected = ("T",) + C.GRID_SHAPE
    if arr.ndim != 4 or arr.shape[1:] != C.GRID_SHAPE or arr.shape[0] < 1:
        raise DataFormatError(f"{name}: expected shape {expected} with T >= 1, got {tuple(arr.shape)}")
    if arr.dtype != dtype:
        raise DataFormatError(f"{name}: expected dtype {np.dtype(dtype)}, got {arr.dtype}")
    return arr


def check_labels(frames: object, name: str = "frames") -> np.ndarray:
    """Validated label volumes: uint8 ``[T, 200, 200, 16]`` with values in 0..17 or 255."""
    arr = _check_volumes(frames, name, np.uint8)
    bad = (arr > C.FREE) & (arr != C.IGNORE)
    if bad.any():
        values = np.unique(arr[bad])[:8].tolist()
        raise DataFormatError(f"{name}: labels must be 0..{C.FREE} or {C.IGNORE}, got {values}")
    return arr


def check_masks(masks: object, name: str = "masks") -> np.ndarray:
    """Validated visibility masks: bool ``[T, 200, 200, 16]``."""
    return _check_volumes(masks, name, np.bool_)


def _runs(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(values, lengths) of the runs of equal values of a 1-D array."""
    starts = np.flatnonzero(np.concatenate([[True], flat[1:] != flat[:-1]]))
    lengths = np.diff(np.append(starts, flat.size))
    return flat[starts], lengths


def _varints(values: np.ndarray) -> bytes:
    """Unsigned LEB128 encoding of non-negative integers ``[N]`` (each < 2**35)."""
    values = values.astype(np.uint64)
    nbytes = np.ones(values.size, np.int64)
    for k in range(1, 5):
        nbytes += values >= (1 << (7 * k))
    offsets = np.concatenate([[0], np.cumsum(nbytes)[:-1]])
    out = np.zeros(int(nbytes.sum()), np.uint8)
    for k in range(int(nbytes.max(initial=0))):
        has = nbytes > k
        byte = (values[has] >> np.uint64(7 * k)) & np.uint64(0x7F)
        more = (nbytes[has] > k + 1).astype(np.uint64) << np.uint64(7)
        out[offsets[has] + k] = (byte | more).astype(np.uint8)
    return out.tobytes()


def _read_varints(data: np.ndarray, count: int) -> np.ndarray:
    """Decode ``count`` LEB128 varints that fill ``data`` (uint8 ``[N]``) exactly; int64 ``[count]``."""
    ends = data < 0x80
    if int(ends.sum()) != count or (data.size and not ends[-1]):
        raise DataFormatError(f"voxel pack: expected {count} run lengths, the data holds {int(ends.sum())}")
    group = np.concatenate([[0], np.cumsum(ends)[:-1]])  # which varint each byte belongs to
    first = np.flatnonzero(np.concatenate([[True], ends[:-1]]))
    position = np.arange(data.size) - first[group]
    if data.size and position.max() > 4:
        raise DataFormatError("voxel pack: a run length is longer than 5 bytes")
    parts = (data & 0x7F).astype(np.int64) << (7 * position)
    return np.bincount(group, weights=parts, minlength=count).astype(np.int64)


def _pack(arr: np.ndarray, kind: int) -> str:
    flat = arr.transpose(0, 3, 1, 2).reshape(arr.shape[0], -1)  # z slowest, then x, then y
    values, lengths = zip(*(_runs(f) for f in flat))
    t, x, y, z = arr.shape
    header = _HEADER.pack(MAGIC, VERSION, kind, t, x, y, z)
    counts = np.array([len(v) for v in values], "<u4").tobytes()
    body = np.concatenate(values).astype(np.uint8).tobytes() + _varints(np.concatenate(lengths))
    return base64.b64encode(zlib.compress(header + counts + body, 9)).decode("ascii")


def pack_frames(frames: np.ndarray) -> str:
    """Base64 text of label volumes uint8 ``[T, 200, 200, 16]`` (ids 0..17, 255 = ignore)."""
    return _pack(check_labels(frames), LABELS)


def pack_masks(masks: np.ndarray) -> str:
    """Base64 text of visibility masks bool ``[T, 200, 200, 16]``."""
    return _pack(check_masks(masks).view(np.uint8), MASK)


def unpack(text: str) -> np.ndarray:
    """Inverse of :func:`pack_frames` (uint8 ``[T, X, Y, Z]``) and :func:`pack_masks` (bool)."""
    try:
        raw = zlib.decompress(base64.b64decode(text, validate=True))
    except (binascii.Error, zlib.error, ValueError) as err:
        raise DataFormatError(f"voxel pack: not base64 zlib data ({err})") from None
    if len(raw) < _HEADER.size:
        raise DataFormatError(f"voxel pack: {len(raw)} bytes, shorter than the {_HEADER.size}-byte header")
    magic, version, kind, t, x, y, z = _HEADER.unpack_from(raw)
    if magic != MAGIC or version != VERSION or kind not in (LABELS, MASK):
        raise DataFormatError(f"voxel pack: unknown header {magic!r} version {version} kind {kind}")
    offset = _HEADER.size
    counts = np.frombuffer(raw, "<u4", t, offset).astype(np.int64)
    offset += 4 * t
    total = int(counts.sum())
    values = np.frombuffer(raw, np.uint8, total, offset)
    lengths = _read_varints(np.frombuffer(raw, np.uint8, offset=offset + total), total)
    ends = np.cumsum(counts)
    if any(int(lengths[e - c: e].sum()) != x * y * z for c, e in zip(counts, ends)):
        raise DataFormatError(f"voxel pack: a volume's runs do not add up to {x}x{y}x{z} voxels")
    flat = np.repeat(values, lengths).reshape(t, z, x, y)
    out = np.ascontiguousarray(flat.transpose(0, 2, 3, 1))
    return out.astype(bool) if kind == MASK else out


def unpack_frames(text: str) -> np.ndarray:
    """Label volumes uint8 ``[T, X, Y, Z]`` from :func:`pack_frames` text."""
    out = unpack(text)
    if out.dtype != np.uint8:
        raise DataFormatError("voxel pack: holds masks, not labels")
    return out


def unpack_masks(text: str) -> np.ndarray:
    """Visibility masks bool ``[T, X, Y, Z]`` from :func:`pack_masks` text."""
    out = unpack(text)
    if out.dtype != np.bool_:
        raise DataFormatError("voxel pack: holds labels, not masks")
    return out
