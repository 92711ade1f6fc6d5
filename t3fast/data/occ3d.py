"""Occ3D-nuScenes reader: ``gts/<scene>/<token>/labels.npz`` plus an OccWorld-style info pickle.

Expected layout::

    <root>/gts/<scene_name>/<token>/labels.npz   # semantics, mask_lidar, mask_camera: uint8 [200, 200, 16]
    <info.pkl>                                   # {"infos": {scene_name: [frame, ...]}, "metadata": {...}}

Each scene's list is time ordered (2 Hz key frames). Keys read from a frame dict:

* ``token`` (str): the sample token, the directory name under ``gts/<scene_name>/``;
* ``ego2global_translation`` (3,), ``ego2global_rotation`` (4,) quaternion w, x, y, z;
* ``gt_ego_fut_trajs`` (6, 2): per-step ego offsets (dx, dy) over the next 6 frames in
  this frame's coordinates; ``gt_ego_fut_masks`` (6,) optional;
* ``gt_ego_fut_cmd`` (3,) optional: the route command, one-hot (turn right, turn left, go
  straight; ``t3fast.data.route``); without it the command is derived from the ego's future;
* ``gt_boxes`` (N, 7): x, y, z, l, w, h, yaw in this frame's coordinates (yaw
  counter-clockwise from +x, length along the heading); ``gt_names`` (N,) nuScenes
  detection names; ``instance_tokens`` (N,) identities across frames (optional);
  ``gt_agent_fut_trajs`` (N, 12) and ``gt_agent_fut_masks`` (N, 6) (used when
  ``instance_tokens`` is absent);
* ``lidar2ego_translation`` / ``lidar2ego_rotation`` (optional): when present, boxes and
  trajectories are taken to be in the LiDAR frame (as in the nuScenes/UniAD info files)
  and are moved into the ego frame.

Labels are Occ3D's (see ``t3fast.data.classes``). Every problem with a file raises
``Occ3DFormatError`` naming the file and the problem. The info pickle is read without running
code from it (plain data and numpy arrays only); scene names and tokens must be plain folder
names, and poses finite with unit quaternions. :func:`read_infos` checks every frame's keys
above (shapes, dtypes, box counts that agree, values finite in float32) and names the scene,
the frame index and token and the field. :func:`read_labels` checks each array's shape and
dtype from its ``.npy`` header before decompressing it.

A small pickle can claim a huge array (nested lists that repeat one inner list object are
stored once), so every field's size is bounded before it becomes an array: a frame holds at
most :data:`MAX_BOXES` boxes, and each field at most the values of its ``FIELD_LIMITS`` entry,
counting every entry of its nested lists.
"""

from __future__ import annotations

import lzma
import reprlib
import zipfile
import zlib
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from t3fast.data import classes as C
from t3fast.data.route import COMMANDS
from t3fast.data.safe_pickle import load_restricted
from t3fast.data.sample import NUM_FUTURE, PRESENT, WINDOW, DrivingSample, build_sample, random_flip, window_starts
from t3fast.errors import DataFormatError
from t3fast.paths import check_name, inside

LABEL_KEYS = ("semantics", "mask_lidar", "mask_camera")

#: nuScenes detection names (and a few raw category prefixes) -> Occ3D class ids
NAME_TO_CLASS = {
    "barrier": C.BARRIER,
    "bicycle": C.BICYCLE,
    "bus": C.BUS,
    "car": C.CAR,
    "construction_vehicle": C.CONSTRUCTION_VEHICLE,
    "motorcycle": C.MOTORCYCLE,
    "pedestrian": C.PEDESTRIAN,
    "traffic_cone": C.TRAFFIC_CONE,
    "trailer": C.TRAILER,
    "truck": C.TRUCK,
}


#: A dataset file is missing, malformed or unsafe; the message names the file and the problem.
Occ3DFormatError = DataFormatError


#: the first bytes of a ``.npy`` file (an ``.npz`` is a zip archive of them)
NPY_MAGIC = b"\x93NUMPY"

#: what a damaged archive or member can raise while it is read: a bad zip structure or CRC
#: (BadZipFile), a corrupt deflate/bzip2/lzma stream (zlib.error, OSError, LZMAError), an
#: unsupported compression method (NotImplementedError), an encrypted member (RuntimeError)
_ARCHIVE_ERRORS: tuple[type[BaseException], ...] = (
    zipfile.BadZipFile, zlib.error, lzma.LZMAError, OSError, EOFError, KeyError, ValueError, NotImplementedError,
    RuntimeError,
)


def read_labels(path: str | Path) -> dict[str, np.ndarray]:
    """Read and check one ``labels.npz``: uint8 ``semantics`` (0..17 or 255) and bool masks, ``[200, 200, 16]``.

    Each array's shape and dtype are checked from its ``.npy`` header before its data is
    decompressed, so a small file that claims a huge array costs nothing to refuse.
    """
    path = Path(path)
    if not path.is_file():
        raise Occ3DFormatError(f"{path}: file not found")
    try:
        with zipfile.ZipFile(path) as archive:
            members = {name[: -len(".npy")]: name for name in archive.namelist() if name.endswith(".npy")}
            missing = [k for k in LABEL_KEYS if k not in members]
            if missing:
                raise Occ3DFormatError(f"{path}: missing array {missing[0]!r} (file has {sorted(members)})")
            arrays = {k: _read_npz_member(archive, members[k], path, k) for k in LABEL_KEYS}
    except Occ3DFormatError:
        raise
    except zipfile.BadZipFile as exc:
        if _starts_with(path, NPY_MAGIC):
            raise Occ3DFormatError(
                f"{path}: a single .npy array, not an .npz archive of {', '.join(LABEL_KEYS)}"
            ) from exc
        raise Occ3DFormatError(f"{path}: not a readable .npz file (BadZipFile: {exc})") from exc
    except _ARCHIVE_ERRORS as exc:
        raise Occ3DFormatError(f"{path}: not a readable .npz file ({type(exc).__name__}: {exc})") from exc
    sem = arrays["semantics"]
    bad = np.unique(sem[(sem > C.FREE) & (sem != C.IGNORE) | (sem < 0)])
    if bad.size:
        raise Occ3DFormatError(f"{path}: 'semantics' has labels outside 0..17 and 255: {bad[:10].tolist()}")
    for key in ("mask_lidar", "mask_camera"):
        if arrays[key].dtype != bool and (arrays[key].max() > 1 or arrays[key].min() < 0):
            raise Occ3DFormatError(f"{path}: {key!r} has values other than 0 and 1")
    return {
        "semantics": np.array(sem, dtype=np.uint8, order="C"),
        "mask_lidar": np.array(arrays["mask_lidar"], dtype=bool, order="C"),
        "mask_camera": np.array(arrays["mask_camera"], dtype=bool, order="C"),
    }


def _starts_with(path: Path, magic: bytes) -> bool:
    with open(path, "rb") as f:
        return f.read(len(magic)) == magic


def _read_npz_member(archive: zipfile.ZipFile, name: str, path: Path, key: str) -> np.ndarray:
    """One label array of an ``.npz``: header checked first, then exactly its bytes read."""
    try:
        with archive.open(name) as stream:
            version = np.lib.format.read_magic(stream)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
            else:
                raise Occ3DFormatError(f"{path}: {key!r} has .npy format version {version}, expected 1.0 or 2.0")
            if dtype.hasobject:
                raise Occ3DFormatError(f"{path}: {key!r} holds Python objects (dtype {dtype}), expected uint8")
            if shape != C.GRID_SHAPE:
                raise Occ3DFormatError(f"{path}: {key!r} has shape {shape}, expected {C.GRID_SHAPE}")
            if dtype.kind not in "biu" or dtype.shape:
                raise Occ3DFormatError(f"{path}: {key!r} has dtype {dtype}, expected uint8")
            size = int(np.prod(shape)) * dtype.itemsize
            data = stream.read(size)
            if len(data) != size:
                raise Occ3DFormatError(f"{path}: {key!r} is truncated ({len(data)} of {size} bytes)")
            if stream.read(1):  # also makes zipfile check the member's CRC
                raise Occ3DFormatError(f"{path}: {key!r} has more data than its header describes")
    except Occ3DFormatError:
        raise
    except _ARCHIVE_ERRORS as exc:
        raise Occ3DFormatError(f"{path}: not a readable .npz file: {key!r} ({type(exc).__name__}: {exc})") from exc
    arr = np.frombuffer(data, dtype=dtype)
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def read_infos(path: str | Path) -> dict[str, list[dict[str, Any]]]:
    """Read an info pickle and return ``{scene_name: [frame, ...]}`` after checking its structure.

    The file is read with :func:`~t3fast.data.safe_pickle.load_restricted` (plain data and
    numpy arrays only, no code). Scene names and tokens must be plain folder names, every
    frame's poses finite with unit quaternions, and its trajectories, boxes, names, instance
    tokens and agent trajectories of the documented shapes, with one row per box and values
    finite in float32, and each frame listed once (not shared between scenes or positions).
    Each field's size is checked against :data:`FIELD_LIMITS` (at most :data:`MAX_BOXES` boxes
    a frame) before it becomes an array.
    """
    path = Path(path)
    if not path.is_file():
        raise Occ3DFormatError(f"{path}: file not found")
    data = load_restricted(path)
    if not isinstance(data, dict) or "infos" not in data:
        raise Occ3DFormatError(f"{path}: expected a dict with key 'infos'")
    infos = data["infos"]
    if not isinstance(infos, dict):
        raise Occ3DFormatError(f"{path}: 'infos' must map scene names to lists of frames, got {type(infos).__name__}")
    # a pickle can reference one frame from many places: a small file would then claim (and
    # cost the checks of) millions of frames, so each frame must be its own object
    owner: dict[int, str] = {}
    for scene, frames in infos.items():
        check_name(scene, f"{path}: scene name")
        if not isinstance(frames, (list, tuple)):
            raise Occ3DFormatError(f"{path}: scene {scene!r} must be a list of frames, got {type(frames).__name__}")
        tokens: set[str] = set()
        for k, frame in enumerate(frames):
            where = f"{path}: scene {scene!r} frame {k}"
            if not isinstance(frame, dict):
                raise Occ3DFormatError(f"{where} must be a dict, got {type(frame).__name__}")
            if id(frame) in owner:
                raise Occ3DFormatError(f"{where} is the same frame as {owner[id(frame)]}: every frame is listed once")
            owner[id(frame)] = f"scene {scene!r} frame {k}"
            for key in ("token", "ego2global_translation", "ego2global_rotation"):
                if key not in frame:
                    raise Occ3DFormatError(f"{where} has no {key!r}")
            token = check_name(frame["token"], f"{where}: token")
            if token in tokens:
                raise Occ3DFormatError(f"{where}: token {token!r} appears twice in the scene")
            tokens.add(token)
            where = f"{where} (token {token!r})"
            _check_pose(frame, "ego2global", where)
            if "lidar2ego_rotation" in frame:
                _check_pose(frame, "lidar2ego", where)
            _check_annotations(frame, where)
    return infos


#: the most boxes a frame may hold (nuScenes frames hold a few hundred)
MAX_BOXES = 20_000
#: the most future steps of a box's trajectory (info files hold 6 or 12)
MAX_AGENT_STEPS = 20
#: values a field of a small fixed shape may hold: room for a wrong shape to be named as such
SMALL_FIELD_VALUES = 1_000
#: how deep lists may nest in a numeric field (a (N, steps, 2) trajectory nests 3 deep); the
#: bound also stops a list that contains itself
MAX_NESTING = 8

#: field -> (the most values it may hold, every entry of its nested lists counted, so that
#: a box row given as a list of 7 numbers counts 8; what that limit is for, for the message)
FIELD_LIMITS: dict[str, tuple[int, str]] = {
    "ego2global_translation": (SMALL_FIELD_VALUES, "a field of shape (3,)"),
    "ego2global_rotation": (SMALL_FIELD_VALUES, "a field of shape (4,)"),
    "lidar2ego_translation": (SMALL_FIELD_VALUES, "a field of shape (3,)"),
    "lidar2ego_rotation": (SMALL_FIELD_VALUES, "a field of shape (4,)"),
    "gt_ego_fut_trajs": (SMALL_FIELD_VALUES, f"a field of shape ({NUM_FUTURE}, 2)"),
    "gt_ego_fut_masks": (SMALL_FIELD_VALUES, f"a field of shape ({NUM_FUTURE},)"),
    "gt_ego_fut_cmd": (SMALL_FIELD_VALUES, f"a field of shape ({len(COMMANDS)},)"),
    "gt_boxes": (MAX_BOXES * (1 + 7), f"{MAX_BOXES:,} boxes"),
    "gt_agent_fut_trajs": (MAX_BOXES * (1 + 3 * MAX_AGENT_STEPS),
                           f"{MAX_BOXES:,} boxes of {MAX_AGENT_STEPS} steps"),
    "gt_agent_fut_masks": (MAX_BOXES * (1 + MAX_AGENT_STEPS), f"{MAX_BOXES:,} boxes of {MAX_AGENT_STEPS} steps"),
}

#: how far from 1 a quaternion's norm may be (float32 round-off is ~1e-7)
QUATERNION_TOLERANCE = 1e-3


def _check_pose(frame: dict[str, Any], prefix: str, where: str) -> None:
    """``<prefix>_translation`` must be 3 finite numbers and ``<prefix>_rotation`` a unit quaternion."""
    _finite_vector(frame.get(f"{prefix}_translation", np.zeros(3)), 3, f"{prefix}_translation", where)
    rotation = _finite_vector(frame[f"{prefix}_rotation"], 4, f"{prefix}_rotation", where)
    norm = float(np.linalg.norm(rotation))
    if abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise Occ3DFormatError(f"{where}: {prefix + '_rotation'!r} is not a unit quaternion (norm {norm:.6g})")


def _finite_vector(value: Any, size: int, key: str, where: str) -> np.ndarray:
    vec = _numbers(value, key, where)
    if vec.shape != (size,):
        raise Occ3DFormatError(f"{where}: {key!r} has shape {vec.shape}, expected ({size},)")
    return vec


def _short_repr() -> reprlib.Repr:
    """A ``repr`` whose work and length stay small however large or deeply shared the value is."""
    short = reprlib.Repr()
    short.maxlevel, short.maxstring, short.maxother = 3, 40, 40
    short.maxlist = short.maxtuple = short.maxdict = short.maxset = 4
    return short


_SHORT_REPR = _short_repr()


def _describe(value: Any) -> str:
    """``str 'xx'``, ``int 5``, ``ndarray <U3 (4,)``: what a field holds, for a message."""
    if isinstance(value, np.ndarray):
        return f"ndarray of {value.dtype} with shape {value.shape}"
    if _huge_int(value):  # its repr is slow, or refused past 4300 digits
        return f"{type(value).__name__} of {value.bit_length()} bits"
    text = _SHORT_REPR.repr(value)
    return f"{type(value).__name__} {text if len(text) <= 40 else text[:37] + '...'}"


def _huge_int(value: Any) -> bool:
    """An int of more than 64 bits: no token or count is that large."""
    return isinstance(value, int) and value.bit_length() > 64


#: what a numeric field may hold besides lists, tuples and arrays (bool is an int)
_NUMBER_TYPES = (int, float, np.integer, np.floating, np.bool_)
#: the number types info files hold, known without an ``isinstance`` per entry
_PLAIN_NUMBER_TYPES = {int, float, bool, np.float64, np.float32, np.int64, np.int32, np.bool_}


def _check_bounded_numbers(value: Any, key: str, where: str) -> None:
    """Refuse ``value`` if its nested lists hold more entries than ``key``'s limit in
    :data:`FIELD_LIMITS`, are nested deeper than :data:`MAX_NESTING`, or hold anything but
    numbers, before numpy builds an array from it.

    Strings are refused here too, as numpy would give every entry the longest one's width.
    """
    limit, allows = FIELD_LIMITS[key]
    _EntryCounter(key, where, limit, allows).count(value, 0)


class _EntryCounter:
    """Counts the entries of a field's nested lists, tuples and arrays, every entry of every
    level included, and refuses the field once the count passes its limit.

    Each list object is counted once and remembered, so lists that repeat one inner list many
    times (which a pickle stores once) cost what the file holds, not what they claim.
    """

    def __init__(self, key: str, where: str, limit: int, allows: str):
        self.key, self.where, self.limit, self.allows = key, where, limit, allows
        self.known: dict[int, int] = {}  # id of a list already counted -> its entries

    def count(self, item: Any, depth: int) -> int:
        """Entries in ``item`` (0 for a number), refusing what is not a number or too large."""
        if isinstance(item, (list, tuple)):
            children = item
        elif isinstance(item, _NUMBER_TYPES):
            return 0
        elif isinstance(item, np.ndarray) and item.dtype.kind in "biuf":
            return self._within_limit(item.size)
        elif isinstance(item, np.ndarray) and item.dtype.kind == "O":
            children = item.ravel()
        else:
            raise Occ3DFormatError(f"{self.where}: {self.key!r} must hold numbers, got {_describe(item)}")
        known = self.known.get(id(item))
        if known is not None:
            return known
        if depth == MAX_NESTING:
            raise Occ3DFormatError(f"{self.where}: {self.key!r} has lists nested more than {MAX_NESTING} deep")
        total = self._within_limit(len(children))
        if not set(map(type, children)) <= _PLAIN_NUMBER_TYPES:  # a row of plain numbers needs no walk
            for child in children:
                if not isinstance(child, _NUMBER_TYPES):
                    total = self._within_limit(total + self.count(child, depth + 1))
        self.known[id(item)] = total
        return total

    def _within_limit(self, total: int) -> int:
        if total > self.limit:
            raise Occ3DFormatError(
                f"{self.where}: {self.key!r} holds more than {self.limit:,} values counting every entry of its "
                f"nested lists (the limit for {self.allows})"
            )
        return total


FLOAT32_MAX = float(np.finfo(np.float32).max)


def _numbers(value: Any, key: str, where: str) -> np.ndarray:
    """``value`` as a float64 array, refused unless it holds numbers that are finite in float32.

    Samples are float32, so a value such as 1e300 (finite in float64) counts as non-finite.
    ``value``'s size is checked against ``key``'s limit first (:func:`_check_bounded_numbers`).
    """
    _check_bounded_numbers(value, key, where)
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:  # e.g. ragged nested lists
        raise Occ3DFormatError(f"{where}: {key!r} is not an array of numbers ({exc})") from exc
    if arr.dtype.kind == "O" and all(isinstance(x, (int, float, np.number)) for x in arr.flat):
        arr = _object_numbers_as_float64(arr, key, where)
    if arr.dtype.kind not in "biuf":
        raise Occ3DFormatError(f"{where}: {key!r} must hold numbers, got {_describe(value)}")
    arr = arr.astype(np.float64)
    finite = np.abs(arr) <= FLOAT32_MAX  # False for NaN, inf and what float32 rounds to inf
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        first = float(arr[tuple(bad)])
        at = f"first at index {tuple(int(i) for i in bad)}: {first!r}" if arr.ndim else repr(first)
        count = int((~finite).sum())
        raise Occ3DFormatError(
            f"{where}: {key!r} has {count} non-finite value{'s' if count > 1 else ''} in float32 ({at})"
        )
    return arr


def _object_numbers_as_float64(arr: np.ndarray, key: str, where: str) -> np.ndarray:
    """An object array of numbers as float64; an integer beyond float64's range is non-finite."""
    try:
        return arr.astype(np.float64)
    except OverflowError:
        index, big = next((i, x) for i, x in np.ndenumerate(arr) if not _fits_float(x))
        raise Occ3DFormatError(
            f"{where}: {key!r} has a non-finite value in float32 "
            f"(first at index {index}: an integer of {big.bit_length()} bits)"
        ) from None


def _fits_float(number: Any) -> bool:
    try:
        float(number)
    except OverflowError:
        return False
    return True


def _strings(value: Any, key: str, where: str, kinds: str = "U") -> np.ndarray:
    """A 1-D sequence (list, tuple or array) of strings (``kinds`` "U") or strings and integers ("Ui")."""
    if isinstance(value, np.ndarray):
        items = value
    elif isinstance(value, (list, tuple)):
        items = np.empty(len(value), dtype=object)
        items[:] = list(value)
    else:
        raise Occ3DFormatError(f"{where}: {key!r} must be a list or array of strings, got {_describe(value)}")
    if items.ndim != 1:
        raise Occ3DFormatError(f"{where}: {key!r} has shape {items.shape}, expected (N,)")
    if len(items) > MAX_BOXES:
        raise Occ3DFormatError(
            f"{where}: {key!r} has {len(items):,} entries, more than the {MAX_BOXES:,} boxes a frame may hold"
        )
    allowed = (str, np.str_) + ((int, np.integer) if "i" in kinds else ())
    if len(items) and items.dtype.kind not in kinds:
        # an integer token of thousands of digits cannot even be turned into a string
        bad = [x for x in items.tolist() if not isinstance(x, allowed) or isinstance(x, bool) or _huge_int(x)]
        if bad:
            raise Occ3DFormatError(f"{where}: {key!r} must hold strings, got {_describe(bad[0])}")
    return items


def _rows(arr: np.ndarray, key: str, where: str, expected: str, boxes: int) -> None:
    """``arr`` has one row per box."""
    if len(arr) != boxes:
        raise Occ3DFormatError(
            f"{where}: {key!r} has {len(arr)} rows (shape {arr.shape}) but 'gt_boxes' has {boxes} boxes; "
            f"expected {expected} with one row per box"
        )


def _check_annotations(frame: dict[str, Any], where: str) -> None:
    """The optional ego trajectory and the boxes with their names, identities and trajectories:
    shapes, lengths that agree with each other, dtypes and float32-finite values."""
    if "gt_ego_fut_trajs" in frame:
        traj = _numbers(frame["gt_ego_fut_trajs"], "gt_ego_fut_trajs", where)
        if traj.shape != (NUM_FUTURE, 2):
            raise Occ3DFormatError(
                f"{where}: 'gt_ego_fut_trajs' has shape {traj.shape}, expected ({NUM_FUTURE}, 2)"
            )
    if "gt_ego_fut_masks" in frame:
        masks = _numbers(frame["gt_ego_fut_masks"], "gt_ego_fut_masks", where)
        if masks.shape != (NUM_FUTURE,):
            raise Occ3DFormatError(f"{where}: 'gt_ego_fut_masks' has shape {masks.shape}, expected ({NUM_FUTURE},)")
    if "gt_ego_fut_cmd" in frame:
        command = _numbers(frame["gt_ego_fut_cmd"], "gt_ego_fut_cmd", where)
        if command.shape != (len(COMMANDS),) or sorted(command.tolist()) != [0, 0, 1]:
            raise Occ3DFormatError(f"{where}: 'gt_ego_fut_cmd' must be a one-hot of {len(COMMANDS)} "
                                   f"({', '.join(COMMANDS)}), got {command.tolist()}")
    boxes = _numbers(frame.get("gt_boxes", np.zeros((0, 7))), "gt_boxes", where)
    if boxes.size == 0:
        boxes = boxes.reshape(0, 7)
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        raise Occ3DFormatError(f"{where}: 'gt_boxes' has shape {boxes.shape}, expected (N, 7)")
    n = len(boxes)
    if n > MAX_BOXES:
        raise Occ3DFormatError(f"{where}: 'gt_boxes' has {n:,} boxes, more than the {MAX_BOXES:,} a frame may hold")
    names = _strings(frame.get("gt_names", []), "gt_names", where)
    if len(names) != n:
        raise Occ3DFormatError(
            f"{where}: 'gt_names' has {len(names)} entries but 'gt_boxes' has {n} boxes (expected one name per box)"
        )
    if "instance_tokens" in frame:
        ids = _strings(frame["instance_tokens"], "instance_tokens", where, kinds="Ui")
        if len(ids) != n:
            raise Occ3DFormatError(
                f"{where}: 'instance_tokens' has {len(ids)} entries but 'gt_boxes' has {n} boxes "
                "(expected one token per box)"
            )
        seen = [str(t) for t in ids.tolist()]
        counts = Counter(seen)
        if len(counts) != len(seen):
            twice = next(t for t in seen if counts[t] > 1)
            raise Occ3DFormatError(f"{where}: 'instance_tokens' has {twice!r} twice")
    steps = None
    if "gt_agent_fut_trajs" in frame:
        trajs = _numbers(frame["gt_agent_fut_trajs"], "gt_agent_fut_trajs", where)
        if n == 0 and trajs.size == 0:
            trajs = trajs.reshape(0, NUM_FUTURE * 2)
        if trajs.ndim == 3 and trajs.shape[2] == 2 and trajs.shape[1] > 0:
            steps = trajs.shape[1]
        elif trajs.ndim == 2 and trajs.shape[1] > 0 and trajs.shape[1] % 2 == 0:
            steps = trajs.shape[1] // 2
        else:
            raise Occ3DFormatError(
                f"{where}: 'gt_agent_fut_trajs' has shape {trajs.shape}, expected (N, 2 * steps), e.g. (N, 12)"
            )
        _rows(trajs, "gt_agent_fut_trajs", where, "(N, 2 * steps)", n)
    if "gt_agent_fut_masks" in frame:
        masks = _numbers(frame["gt_agent_fut_masks"], "gt_agent_fut_masks", where)
        if n == 0 and masks.size == 0:
            masks = masks.reshape(0, steps or NUM_FUTURE)
        expected = f"(N, {steps})" if steps else "(N, steps)"
        if masks.ndim != 2 or (steps is not None and masks.shape[1] != steps):
            raise Occ3DFormatError(
                f"{where}: 'gt_agent_fut_masks' has shape {masks.shape}, expected {expected} "
                "(one mask per step of 'gt_agent_fut_trajs')"
            )
        _rows(masks, "gt_agent_fut_masks", where, expected, n)


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """3x3 rotation of a quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _transform(translation: Any, rotation: Any) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = quaternion_matrix(np.asarray(rotation))
    m[:3, 3] = np.asarray(translation, dtype=np.float64)
    return m


def _lidar2ego(frame: dict[str, Any]) -> np.ndarray:
    if "lidar2ego_rotation" not in frame:
        return np.eye(4)
    return _transform(frame.get("lidar2ego_translation", np.zeros(3)), frame["lidar2ego_rotation"])


def _boxes_to_ego(boxes: np.ndarray, l2e: np.ndarray) -> np.ndarray:
    out = boxes.copy()
    out[:, :3] = boxes[:, :3] @ l2e[:3, :3].T + l2e[:3, 3]
    out[:, 6] = boxes[:, 6] + np.arctan2(l2e[1, 0], l2e[0, 0])
    return out


def _class_ids(names: Any) -> np.ndarray:
    """Class ids of detection names; unknown names map to ``others``."""
    out = [NAME_TO_CLASS.get(str(n), NAME_TO_CLASS.get(str(n).split(".")[-1], C.OTHERS)) for n in names]
    return np.array(out, dtype=np.int64).reshape(-1)


class Occ3DNuScenes(Dataset):
    """11-frame ``DrivingSample``s from Occ3D-nuScenes (or anything in its layout).

    Args:
        data_root: directory holding ``gts/``.
        info_path: the info pickle (OccWorld-style ``nuscenes_infos_<split>_temporal_*.pkl``).
        stride: frames between the starts of consecutive windows of a scene.
        flip: apply ``random_flip``.
        scenes: optional subset of scene names.
    """

    def __init__(
        self,
        data_root: str | Path,
        info_path: str | Path,
        stride: int = 1,
        flip: bool = False,
        scenes: list[str] | None = None,
    ):
        self.root = Path(data_root)
        self.info_path = Path(info_path)
        infos = read_infos(self.info_path)
        if scenes is not None:
            unknown = sorted(set(scenes) - set(infos))
            if unknown:
                raise Occ3DFormatError(f"{self.info_path}: no scene named {unknown[0]!r}")
            infos = {s: infos[s] for s in scenes}
        self.infos = infos
        self.flip = flip
        self.index = [(scene, start) for scene, frames in infos.items() for start in window_starts(len(frames), stride)]

    def __len__(self) -> int:
        return len(self.index)

    def label_path(self, scene: str, token: str) -> Path:
        """``<root>/gts/<scene>/<token>/labels.npz``; the names must not leave ``gts/``."""
        return inside(self.root / "gts", check_name(scene, "scene name"), check_name(token, "token"), "labels.npz")

    def __getitem__(self, index: int) -> DrivingSample:
        if not 0 <= index < len(self):
            raise IndexError(index)
        scene, start = self.index[index]
        frames = self.infos[scene][start : start + WINDOW]
        labels = [read_labels(self.label_path(scene, f["token"])) for f in frames]
        poses = np.stack([_transform(f["ego2global_translation"], f["ego2global_rotation"]) for f in frames])
        with np.errstate(over="ignore", invalid="ignore"):  # overflow is refused just below
            boxes, valid, classes = self._tracks(scene, frames)
            sample = build_sample(
                occ=np.stack([lab["semantics"] for lab in labels]),
                mask_camera=np.stack([lab["mask_camera"] for lab in labels]),
                ego_poses=poses,
                boxes=boxes,
                box_valid=valid,
                box_labels=classes,
                scene=scene,
                start=start,
                future_actions=self._future_actions(scene, start, frames[PRESENT]),
                command=int(np.argmax(frames[PRESENT]["gt_ego_fut_cmd"])) if "gt_ego_fut_cmd" in frames[PRESENT]
                else None,
            )
        self._check_finite(sample, frames)
        return random_flip(sample) if self.flip else sample

    def _check_finite(self, sample: DrivingSample, frames: list[dict[str, Any]]) -> None:
        """Every value read is finite in float32, but poses far apart can still overflow once
        combined (a relative pose, a step between frames): refuse such a window."""
        for key in ("past_actions", "future_actions", "boxes", "ego_poses"):
            if not torch.isfinite(getattr(sample, key)).all():
                raise Occ3DFormatError(
                    f"{self.info_path}: scene {sample.scene!r} frames {sample.start}..{sample.start + WINDOW - 1} "
                    f"(tokens {frames[0]['token']!r}..{frames[-1]['token']!r}): the window's {key} are not finite "
                    "in float32; its poses or boxes are too large"
                )

    def _future_actions(self, scene: str, start: int, frame: dict[str, Any]) -> np.ndarray | None:
        """The present frame's ``gt_ego_fut_trajs`` in ego coordinates (None: use the poses).

        Shapes and values were checked by :func:`read_infos`.
        """
        if "gt_ego_fut_trajs" not in frame:
            return None
        traj = np.asarray(frame["gt_ego_fut_trajs"], dtype=np.float64)
        masks = np.asarray(frame.get("gt_ego_fut_masks", np.ones(NUM_FUTURE)), dtype=np.float64)
        if not np.all(masks > 0):
            return None
        return traj @ _lidar2ego(frame)[:2, :2].T

    def _tracks(self, scene: str, frames: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Boxes ``[11, A, 7]`` (each frame's own coordinates), validity ``[11, A]``, class ids ``[A]``."""
        per_frame = []
        for f in frames:
            # shapes, lengths and values were checked by read_infos
            b = np.asarray(f.get("gt_boxes", np.zeros((0, 7))), dtype=np.float64).reshape(-1, 7)
            names = f.get("gt_names", [])
            per_frame.append((_boxes_to_ego(b, _lidar2ego(f)), _class_ids(names)))
        if all("instance_tokens" in f for f in frames):
            ids = sorted({str(t) for f in frames for t in f["instance_tokens"]})
            col = {t: i for i, t in enumerate(ids)}
            boxes = np.zeros((WINDOW, len(ids), 7))
            valid = np.zeros((WINDOW, len(ids)), dtype=bool)
            classes = np.zeros(len(ids), dtype=np.int64)
            for k, (f, (b, c)) in enumerate(zip(frames, per_frame)):
                cols = [col[str(t)] for t in f["instance_tokens"]]
                boxes[k, cols], valid[k, cols], classes[cols] = b, True, c
            return boxes, valid, classes
        # no identities: the present frame's agents, carried forward by their future trajectories
        present = frames[PRESENT]
        b, c = per_frame[PRESENT]
        boxes = np.zeros((WINDOW, len(b), 7))
        valid = np.zeros((WINDOW, len(b)), dtype=bool)
        boxes[PRESENT], valid[PRESENT] = b, True
        if "gt_agent_fut_trajs" in present and len(b):
            rot = _lidar2ego(present)[:2, :2]
            steps = np.asarray(present["gt_agent_fut_trajs"], dtype=np.float64).reshape(len(b), -1, 2) @ rot.T
            masks = np.asarray(present.get("gt_agent_fut_masks", np.ones(steps.shape[:2])), dtype=np.float64) > 0
            pos = b[:, None, :2] + np.cumsum(steps, axis=1)
            poses = [_transform(f["ego2global_translation"], f["ego2global_rotation"]) for f in frames]
            for k in range(min(steps.shape[1], WINDOW - PRESENT - 1)):
                t = PRESENT + 1 + k
                moved = b.copy()
                moved[:, :2] = pos[:, k]
                # boxes are stored in each frame's own coordinates: present -> frame t
                to_t = np.linalg.inv(poses[t]) @ poses[PRESENT]
                moved[:, :2] = moved[:, :2] @ to_t[:2, :2].T + to_t[:2, 3]
                moved[:, 6] += np.arctan2(to_t[1, 0], to_t[0, 0])
                boxes[t] = moved
                valid[t] = np.cumprod(masks, axis=1)[:, k] > 0
        return boxes, valid, c
