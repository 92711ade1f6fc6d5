"""Packing label volumes and masks: exact round trips and clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from t3fast.data import classes as C
from t3fast.errors import DataFormatError
from t3fast.viz.voxel_pack import pack_frames, pack_masks, unpack_frames, unpack_masks


def test_random_labels_round_trip_with_ignore():
    rng = np.random.default_rng(0)
    ids = np.array([*range(C.FREE + 1), C.IGNORE], np.uint8)
    frames = rng.choice(ids, size=(2, *C.GRID_SHAPE))
    frames[1, :, :, 8:] = C.FREE  # long runs next to single voxels
    out = unpack_frames(pack_frames(frames))
    assert out.dtype == np.uint8 and out.shape == frames.shape
    np.testing.assert_array_equal(out, frames)


def test_synthetic_labels_and_masks_round_trip_compactly(synthetic_window):
    occ, mask = synthetic_window["occ"], synthetic_window["mask"]
    text = pack_frames(occ)
    np.testing.assert_array_equal(unpack_frames(text), occ)
    assert len(text) < 0.01 * occ.nbytes  # the runs along the layers are long
    out = unpack_masks(pack_masks(mask))
    assert out.dtype == np.bool_
    np.testing.assert_array_equal(out, mask)


@pytest.mark.parametrize(
    "frames, words",
    [
        (np.zeros((200, 200, 16), np.uint8), ["frames", "shape", "(200, 200, 16)"]),
        (np.zeros((1, 100, 200, 16), np.uint8), ["frames", "shape", "(1, 100, 200, 16)"]),
        (np.zeros((1, 200, 200, 16), np.int64), ["frames", "dtype uint8", "int64"]),
        (np.full((1, 200, 200, 16), 18, np.uint8), ["frames", "0..17 or 255", "[18]"]),
    ],
)
def test_bad_labels_say_what_is_wrong(frames, words):
    with pytest.raises(DataFormatError) as err:
        pack_frames(frames)
    assert all(w in str(err.value) for w in words), str(err.value)


def test_bad_masks_and_mixed_up_packs():
    with pytest.raises(DataFormatError, match="masks: expected dtype bool, got uint8"):
        pack_masks(np.zeros((1, *C.GRID_SHAPE), np.uint8))
    labels = pack_frames(np.full((1, *C.GRID_SHAPE), C.FREE, np.uint8))
    with pytest.raises(DataFormatError, match="labels, not masks"):
        unpack_masks(labels)
    with pytest.raises(DataFormatError, match="not base64 zlib"):
        unpack_frames("not a pack")
