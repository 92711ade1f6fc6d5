"""Info fields are bounded before they become arrays: a small pickle whose nested lists share
one inner list many times claims a huge array, and must be refused without building it."""

from __future__ import annotations

import pickle
import tracemalloc

import numpy as np
import pytest

from t3fast.data.occ3d import MAX_BOXES, read_infos
from t3fast.errors import DataFormatError

#: far above what reading a few small frames needs, far below what the claimed arrays would take
PEAK_BYTES = 32 * 2**20


@pytest.fixture
def infos(exported):
    """A fresh copy of the exported scenes' info dict, to corrupt."""
    with open(exported[1], "rb") as f:
        return pickle.load(f)


def shared_nested(shape: tuple[int, ...], leaf: object = 0.0) -> list:
    """Nested lists of ``shape`` in which every level repeats one inner list object: pickle
    stores each level once, so the file stays small whatever the shape claims."""
    value = leaf
    for size in reversed(shape):
        value = [value] * size
    return value


def read_with_peak(path) -> tuple[BaseException | None, int]:
    """(the exception ``read_infos(path)`` raised, or None; the peak bytes it allocated)."""
    tracemalloc.start()
    try:
        read_infos(path)
    except BaseException as exc:  # noqa: BLE001 - a MemoryError is what the old reader ended in
        return exc, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return None, 0


def _containing_itself() -> list:
    looped: list = [[0.0] * 7]
    looped.append(looped)
    return looped


#: field -> (a shared nested value claiming a huge array, what the refusal must say)
HUGE_CLAIMS = {
    "gt_boxes": (lambda: shared_nested((1000, 1000, 1000, 7)),
                 f"'gt_boxes' holds more than {8 * MAX_BOXES:,} values"),
    "gt_boxes rows": (lambda: shared_nested((10 * MAX_BOXES, 7)), f"{8 * MAX_BOXES:,} values"),
    "gt_agent_fut_trajs": (lambda: shared_nested((1000, 1000, 1000, 2)), "'gt_agent_fut_trajs' holds more than"),
    "gt_agent_fut_masks": (lambda: shared_nested((1000, 1000, 1000)), "'gt_agent_fut_masks' holds more than"),
    "gt_ego_fut_trajs": (lambda: shared_nested((1000, 1000, 1000, 2)), "'gt_ego_fut_trajs' holds more than"),
    "gt_ego_fut_masks": (lambda: shared_nested((1000, 1000, 1000)), "'gt_ego_fut_masks' holds more than"),
    "gt_ego_fut_cmd": (lambda: shared_nested((1000, 1000, 1000)), "'gt_ego_fut_cmd' holds more than"),
    "ego2global_translation": (lambda: shared_nested((1000, 1000, 1000)), "'ego2global_translation' holds more"),
    "ego2global_rotation": (lambda: shared_nested((1000, 1000, 1000)), "'ego2global_rotation' holds more than"),
    "lidar2ego_translation": (lambda: shared_nested((1000, 1000, 1000)), "'lidar2ego_translation' holds more"),
    # lists of empty lists: no numbers at all, but a billion lists for numpy to walk
    "gt_boxes of empty lists": (lambda: shared_nested((1000, 1000, 1000, 0)), "'gt_boxes' holds more than"),
    # one long string repeated: numpy would make an array of that width per entry
    "gt_boxes of a long string": (lambda: ["x" * 2**20] * 10_000, "'gt_boxes' must hold numbers, got str 'xxx"),
    "gt_boxes containing itself": (lambda: _containing_itself(), "'gt_boxes' has lists nested more than 8 deep"),
    "gt_names": (lambda: shared_nested((1000, 1000, 1000), "car"), "'gt_names' must hold strings, got list [["),
    "gt_names too many": (lambda: ["car"] * (MAX_BOXES + 1), f"'gt_names' has {MAX_BOXES + 1:,} entries, more than"),
    "instance_tokens": (lambda: shared_nested((1000, 1000, 1000), "a"), "'instance_tokens' must hold strings"),
}


@pytest.mark.parametrize("case", sorted(HUGE_CLAIMS))
def test_small_file_claiming_a_huge_field_is_refused_before_allocating(infos, tmp_path, case):
    make, expected = HUGE_CLAIMS[case]
    key = case.split(" ")[0]
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][3]
    frame[key] = make()
    if key.startswith("lidar2ego"):
        frame["lidar2ego_rotation"] = [1.0, 0.0, 0.0, 0.0]
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(infos))
    assert path.stat().st_size < 2**20 + 2**19  # a small file, whatever it claims

    error, peak = read_with_peak(path)
    assert isinstance(error, DataFormatError), repr(error)
    message = str(error)
    assert message.startswith(f"{path}: scene {scene!r} frame 3 (token {frame['token']!r}): {key!r} "), message
    assert expected in message and "\n" not in message and len(message) < 400, message
    assert peak < PEAK_BYTES, f"read_infos allocated {peak / 2**20:.0f} MiB before refusing the file"


def test_box_count_limit_is_named(infos, tmp_path):
    """An array of more boxes than a frame may hold is refused with the limit in the message."""
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][0]
    n = MAX_BOXES + 1
    frame["gt_boxes"] = np.zeros((n, 7), dtype=np.float32)
    frame["gt_names"] = np.array(["car"] * n)
    del frame["instance_tokens"], frame["gt_agent_fut_trajs"], frame["gt_agent_fut_masks"]
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(infos))
    with pytest.raises(DataFormatError, match=rf"frame 0 \(token .*\): 'gt_boxes' has {n:,} boxes, "
                                              rf"more than the {MAX_BOXES:,} a frame may hold$"):
        read_infos(path)


def test_frame_of_the_most_boxes_allowed_loads(infos, tmp_path):
    """The limits leave room: a frame of exactly MAX_BOXES boxes, all fields as nested lists, loads."""
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][0]
    n = MAX_BOXES
    frame["gt_boxes"] = [[float(i), 0.0, 0.0, 4.0, 2.0, 1.5, 0.0] for i in range(n)]
    frame["gt_names"] = ["car"] * n
    frame["instance_tokens"] = [f"t{i}" for i in range(n)]
    frame["gt_agent_fut_trajs"] = [[[0.5, 0.0]] * 6 for _ in range(n)]
    frame["gt_agent_fut_masks"] = [[1.0] * 6 for _ in range(n)]
    path = tmp_path / "big.pkl"
    path.write_bytes(pickle.dumps(infos))
    assert len(read_infos(path)[scene][0]["gt_boxes"]) == n


@pytest.mark.parametrize(("key", "value", "at"), [("gt_boxes", [[10**400] * 7], "(0, 0)"),
                                                 ("gt_ego_fut_masks", [2**1024] * 6, "(0,)")])
def test_integers_too_large_for_float_are_non_finite(infos, tmp_path, key, value, at):
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][3]
    frame[key] = value
    if key == "gt_boxes":
        for other in ("gt_names", "instance_tokens", "gt_agent_fut_trajs", "gt_agent_fut_masks"):
            frame[other] = frame[other][:1]
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(infos))
    with pytest.raises(DataFormatError) as error:
        read_infos(path)
    bits = value[0][0].bit_length() if key == "gt_boxes" else value[0].bit_length()
    assert str(error.value).endswith(f"frame 3 (token {frame['token']!r}): {key!r} has a non-finite value in float32 "
                                     f"(first at index {at}: an integer of {bits} bits)")


@pytest.mark.parametrize("key", ["gt_names", "instance_tokens"])
def test_huge_integer_among_names_or_tokens_is_described_in_one_short_line(infos, tmp_path, key):
    """Python refuses to print an int of over 4300 digits; the message gives its size instead."""
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][3]
    frame[key] = [10**5000] * len(frame["gt_boxes"])
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(infos))
    expected = rf"frame 3 \(token .*\): '{key}' must hold strings, got int of 16610 bits$"
    with pytest.raises(DataFormatError, match=expected):
        read_infos(path)


@pytest.mark.parametrize("where", ["first", "last"])
def test_repeated_instance_token_among_many_is_named(infos, tmp_path, where):
    """The first token (in order) that occurs twice is named, also among the most boxes a frame may hold."""
    scene = next(iter(infos["infos"]))
    frame = infos["infos"][scene][3]
    n = MAX_BOXES
    tokens = [f"t{i}" for i in range(n)]
    if where == "first":
        tokens[-1] = tokens[0]  # 't0' occurs first and again at the end
    else:
        tokens[-1] = tokens[-2]
    frame["gt_boxes"] = np.zeros((n, 7))
    frame["gt_names"] = ["car"] * n
    frame["instance_tokens"] = tokens
    del frame["gt_agent_fut_trajs"], frame["gt_agent_fut_masks"]
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(infos))
    twice = tokens[-1]
    with pytest.raises(DataFormatError, match=rf"frame 3 \(token .*\): 'instance_tokens' has {twice!r} twice$"):
        read_infos(path)


def test_a_frame_listed_twice_is_refused(infos, tmp_path):
    """A pickle that lists one frame object in many scenes claims frames it does not hold (10,000
    scenes of one shared frame list cost hours of checks): each frame must be listed once."""
    scenes = list(infos["infos"])
    frames = infos["infos"][scenes[0]]
    infos["infos"] = {f"copy{i:05d}": frames for i in range(10_000)}
    path = tmp_path / "shared.pkl"
    path.write_bytes(pickle.dumps(infos))
    assert path.stat().st_size < 2 * len(pickle.dumps(frames))
    with pytest.raises(DataFormatError, match=r"scene 'copy00001' frame 0 is the same frame as "
                                              r"scene 'copy00000' frame 0: every frame is listed once$"):
        read_infos(path)
