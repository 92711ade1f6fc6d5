"""triplane_decode refuses impossible grids and empty planes with a message, not a cast or
allocator error."""

from __future__ import annotations

import pytest
import torch

from t3fast.ops import triplane_decode
from tests.ops.test_triplane_decode import make_inputs


@pytest.mark.parametrize("grid", [(2**64, 1, 1), (2**63, 1)])
def test_grid_beyond_int64_is_a_value_error(grid):
    planes, weights, biases = make_inputs(1, 4, (3, 3, 3), [], 1)
    with pytest.raises(ValueError, match=r"grid sizes must fit in 64 bits"):
        triplane_decode(*planes, weights, biases, grid=grid, pe_freqs=1)


@pytest.mark.parametrize("argmax", [False, True])
def test_grid_larger_than_memory_is_refused_up_front(argmax):
    planes, weights, biases = make_inputs(2, 4, (3, 3, 3), [], 1)
    what = "labels" if argmax else "logits of 11 classes"
    with pytest.raises(ValueError, match=rf"grid \(100000, 100000, 1000\) at batch 2 needs .* TB of {what}"):
        triplane_decode(*planes, weights, biases, grid=(100_000, 100_000, 1000), pe_freqs=1, argmax=argmax)


def test_grid_of_floats():
    planes, weights, biases = make_inputs(1, 4, (3, 3, 3), [], 1)
    with pytest.raises(ValueError, match=r"grid must hold integers, got \(2\.5, 2, 2\)"):
        triplane_decode(*planes, weights, biases, grid=(2.5, 2, 2), pe_freqs=1)


def test_planes_without_channels():
    planes, weights, biases = make_inputs(1, 0, (3, 3, 3), [], 1)
    with pytest.raises(RuntimeError, match=r"planes must have at least one channel, got xy \[1, 0, 3, 3\]"):
        triplane_decode(*planes, weights, biases, grid=(2, 2, 2), pe_freqs=1)


def test_ordinary_grids_still_decode():
    planes, weights, biases = make_inputs(1, 4, (3, 3, 3), [], 1)
    assert triplane_decode(*planes, weights, biases, grid=torch.Size([4, 3, 2]), pe_freqs=1).shape == (1, 4, 3, 2, 11)
