"""Hostile ``labels.npz`` files: refused in one line naming the file and the array, and
refused from their headers before any large array is decompressed."""

from __future__ import annotations

import io
import re
import shutil
import tracemalloc
import zipfile

import numpy as np
import pytest

from t3fast.commands.main import main
from t3fast.data import classes as C
from t3fast.data.occ3d import Occ3DFormatError, Occ3DNuScenes, read_labels
from t3fast.data.occ3d_frames import Occ3DFrames

#: far below what any of the hostile files below would cost if their arrays were read
PEAK_LIMIT = 16 * 2**20


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _npy_header(shape: tuple[int, ...], descr: str = "|u1") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _write_npz(path, members: dict[str, bytes]) -> None:
    """An ``.npz`` with the given raw ``.npy`` members (deflated, as np.savez_compressed writes)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    good = _npy(np.ones(C.GRID_SHAPE, np.uint8))
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for key in ("semantics", "mask_lidar", "mask_camera"):
            archive.writestr(f"{key}.npy", members.get(key, good))


def _peak_of(fn, *args) -> tuple[int, BaseException | None]:
    tracemalloc.start()
    tracemalloc.reset_peak()
    error = None
    try:
        fn(*args)
    except Exception as exc:  # noqa: BLE001 - the caller checks what was raised
        error = exc
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak, error


def test_header_claiming_a_huge_array_is_refused_without_allocating_it(tmp_path):
    path = tmp_path / "labels.npz"
    # 900 MB claimed, a few KB of zeros behind the header
    _write_npz(path, {"semantics": _npy_header((30000, 30000)) + bytes(4096)})
    assert path.stat().st_size < 100_000
    peak, error = _peak_of(read_labels, path)
    assert isinstance(error, Occ3DFormatError)
    assert str(path) in str(error) and "'semantics' has shape (30000, 30000), expected (200, 200, 16)" in str(error)
    assert peak < PEAK_LIMIT


def test_decompression_bomb_is_refused_from_its_header(tmp_path):
    path = tmp_path / "gts" / "scene-1" / "tok" / "labels.npz"
    path.parent.mkdir(parents=True)
    shape = (8000, 8000)  # 64 MB of zeros that deflate to ~60 KB
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        with archive.open("semantics.npy", "w") as member:
            member.write(_npy_header(shape))
            for _ in range(shape[0]):
                member.write(bytes(shape[1]))
        for key in ("mask_lidar", "mask_camera"):
            archive.writestr(f"{key}.npy", _npy(np.ones(C.GRID_SHAPE, np.uint8)))
    assert path.stat().st_size < 1_000_000
    peak, error = _peak_of(read_labels, path)
    assert isinstance(error, Occ3DFormatError)
    assert str(path) in str(error) and "'semantics' has shape (8000, 8000)" in str(error)
    assert peak < PEAK_LIMIT


def test_good_file_costs_little_and_fortran_order_reads_back(tmp_path):
    sem = np.full(C.GRID_SHAPE, C.FREE, np.uint8)
    sem[3, 7, 1:5] = C.CAR
    path = tmp_path / "labels.npz"
    np.savez_compressed(path, semantics=np.asfortranarray(sem), mask_lidar=np.ones(C.GRID_SHAPE, np.uint8),
                        mask_camera=np.zeros(C.GRID_SHAPE, bool))
    peak, error = _peak_of(read_labels, path)
    assert error is None and peak < PEAK_LIMIT
    out = read_labels(path)
    assert np.array_equal(out["semantics"], sem) and out["semantics"].flags.c_contiguous
    assert out["semantics"].flags.writeable and not out["mask_camera"].any() and out["mask_lidar"].all()


@pytest.mark.parametrize(
    ("member", "problem"),
    [
        (_npy(np.array([None, 1], dtype=object)), "'semantics' holds Python objects"),
        (_npy(np.zeros(C.GRID_SHAPE, "<U1")), "'semantics' has dtype <U1, expected uint8"),
        (_npy_header(C.GRID_SHAPE) + bytes(1000), "'semantics' is truncated (1000 of 640000 bytes)"),
        (_npy(np.zeros(C.GRID_SHAPE, np.uint8)) + b"x", "'semantics' has more data than its header describes"),
        (b"not an npy member", "not a readable .npz file: 'semantics'"),
    ],
    ids=["object dtype", "string dtype", "truncated", "trailing data", "no npy magic"],
)
def test_bad_members_name_file_and_array(tmp_path, member, problem):
    path = tmp_path / "labels.npz"
    _write_npz(path, {"semantics": member})
    with pytest.raises(Occ3DFormatError) as err:
        read_labels(path)
    assert str(path) in str(err.value) and problem in str(err.value)


def _npy_under_npz_name(path) -> None:
    with open(path, "wb") as f:
        np.save(f, np.full(C.GRID_SHAPE, C.FREE, np.uint8))


def _corrupt_deflate(path) -> None:
    """Make the deflate stream of ``semantics.npy`` start with a reserved block type."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("semantics.npy")
    data = bytearray(path.read_bytes())
    name_len = int.from_bytes(data[info.header_offset + 26 : info.header_offset + 28], "little")
    extra_len = int.from_bytes(data[info.header_offset + 28 : info.header_offset + 30], "little")
    data[info.header_offset + 30 + name_len + extra_len] = 0xFF  # BFINAL=1, BTYPE=11 (reserved)
    path.write_bytes(bytes(data))


CORRUPTIONS = {
    "npy under the npz name": (_npy_under_npz_name, "a single .npy array, not an .npz archive"),
    "corrupt deflate stream": (_corrupt_deflate, "not a readable .npz file: 'semantics' (error:"),
}


@pytest.mark.parametrize("corruption", sorted(CORRUPTIONS))
def test_corrupt_files_are_one_data_error(tmp_path, corruption):
    make, problem = CORRUPTIONS[corruption]
    path = tmp_path / "labels.npz"
    np.savez_compressed(path, **{k: np.ones(C.GRID_SHAPE, np.uint8) for k in ("semantics", "mask_lidar",
                                                                           "mask_camera")})
    make(path)
    with pytest.raises(Occ3DFormatError) as err:
        read_labels(path)
    assert str(path) in str(err.value) and problem in str(err.value)


@pytest.fixture
def damaged(exported, tmp_path, request):
    """A copy of the exported data with the present frame of the first window damaged."""
    root, info = exported
    copy = tmp_path / "data"
    shutil.copytree(root, copy)
    shutil.copy(info, copy / info.name)
    dataset = Occ3DNuScenes(copy, copy / info.name)
    scene, start = dataset.index[0]
    victim = dataset.label_path(scene, dataset.infos[scene][start + 4]["token"])
    make, problem = CORRUPTIONS[request.param]
    make(victim)
    return copy, copy / info.name, victim, problem


@pytest.mark.parametrize("damaged", sorted(CORRUPTIONS), indirect=True)
@pytest.mark.parametrize("command", ["view", "data stats --root", "data stats --occ3d", "data render"])
def test_every_command_reports_a_corrupt_file_in_one_line(damaged, command, tmp_path, capsys):
    root, info, victim, problem = damaged
    argv = {
        "view": ["view", "--data", str(root), "--out", str(tmp_path / "v.html")],
        "data stats --root": ["data", "stats", "--root", str(root), "--info", str(info)],
        "data stats --occ3d": ["data", "stats", "--occ3d", str(root)],
        "data render": ["data", "render", "--root", str(root), "--info", str(info), "--out", str(tmp_path / "r.png")],
    }[command]
    assert main(argv) == 1
    err = capsys.readouterr().err
    lines = re.findall(r"t3fast [a-z ]+: [^\r\n]*\n", err)  # progress bars share stderr
    assert len(lines) == 1 and "Traceback" not in err
    assert lines[0].startswith(f"t3fast {command.split(' --')[0]}: ")
    assert str(victim) in lines[0] and problem in lines[0]


@pytest.mark.parametrize("damaged", sorted(CORRUPTIONS), indirect=True)
def test_datasets_report_a_corrupt_file(damaged):
    root, info, victim, problem = damaged
    with pytest.raises(Occ3DFormatError) as err:
        Occ3DNuScenes(root, info)[0]
    assert str(victim) in str(err.value) and problem in str(err.value)
    frames = Occ3DFrames(root, info)
    index = frames.frames.index((victim.parent.parent.name, victim.parent.name))
    with pytest.raises(Occ3DFormatError) as err:
        frames[index]
    assert str(victim) in str(err.value) and problem in str(err.value)
