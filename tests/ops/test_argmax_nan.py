"""triplane_decode's argmax mode returns what torch.argmax returns, NaN and inf included."""

from __future__ import annotations

import math

import torch

from t3fast.ops import reference, triplane_decode
from tests.ops.test_triplane_decode import make_inputs, random_points

GRID = (6, 5, 4)


def assert_argmax_parity(planes, weights, biases, **query) -> torch.Tensor:
    """Fused labels equal torch.argmax of the reference logits and of the fused logits."""
    labels = triplane_decode(*planes, weights, biases, argmax=True, **query)
    ref_logits = reference.triplane_decode(*planes, weights, biases, **query)
    fused_logits = triplane_decode(*planes, weights, biases, **query)
    assert torch.equal(labels.long(), ref_logits.argmax(-1))
    assert torch.equal(labels.long(), fused_logits.argmax(-1))
    return labels


def test_nan_bias_wins_like_torch(device):
    planes, weights, biases = make_inputs(2, 5, (3, 4, 6), [16], 2, device=device)
    biases[-1][7] = math.nan
    labels = assert_argmax_parity(planes, weights, biases, grid=GRID, pe_freqs=2)
    assert (labels == 7).all()  # the NaN class, although other logits are larger numbers


def test_first_nan_wins_and_all_nan_rows(device):
    planes, weights, biases = make_inputs(1, 5, (3, 4, 6), [], 2, device=device)
    biases[-1][4] = biases[-1][9] = math.nan
    assert (assert_argmax_parity(planes, weights, biases, grid=GRID, pe_freqs=2) == 4).all()
    biases[-1].fill_(math.nan)
    assert (assert_argmax_parity(planes, weights, biases, grid=GRID, pe_freqs=2) == 0).all()


def test_inf_weights_mix_nan_and_inf_rows(device):
    # a hidden unit that ReLU zeroes times inf gives NaN, a positive one inf: rows of both kinds
    planes, weights, biases = make_inputs(2, 5, (3, 4, 6), [16], 2, device=device)
    weights[-1][3, 0] = math.inf
    weights[-1][8, 1] = -math.inf
    points = random_points(2, 300, device=device)
    labels = assert_argmax_parity(planes, weights, biases, points=points, pe_freqs=2)
    logits = reference.triplane_decode(*planes, weights, biases, points=points, pe_freqs=2)
    assert logits.isnan().any() and logits.isinf().any()  # the case is really exercised
    assert len(labels.unique()) > 1


def test_nan_planes(device):
    planes, weights, biases = make_inputs(1, 5, (3, 4, 6), [16], 2, device=device)
    planes[0][0, :, 1, 2] = math.nan  # every logit of the voxels that read this texel is NaN
    labels = assert_argmax_parity(planes, weights, biases, grid=GRID, pe_freqs=2)
    assert (labels == 0).any()
