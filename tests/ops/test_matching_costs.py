"""matching_costs: parity with the reference forward and backward (odd sizes, radii past the
plane, one row or column, non-contiguous and empty inputs), gradcheck, opcheck, and bad input."""

from __future__ import annotations

import pytest
import torch

from t3fast.ops import matching_costs, reference

SHAPES_RADII = [((2, 8, 100, 100), 6), ((1, 3, 7, 5), 2), ((2, 5, 1, 9), 3), ((1, 4, 6, 1), 4), ((1, 2, 3, 3), 5),
                ((3, 16, 20, 30), 0), ((1, 1, 1, 1), 1)]


def rand(*shape, device="cpu", dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=dtype).to(device)


@pytest.mark.parametrize("shape, radius", SHAPES_RADII)
def test_matching_costs_match_the_reference(device, shape, radius):
    present = rand(*shape, device=device, seed=1).requires_grad_()
    previous = rand(*shape, device=device, seed=2).requires_grad_()
    got = matching_costs(present, previous, radius)
    want = reference.matching_costs(present, previous, radius)
    assert got.shape == (shape[0], (2 * radius + 1) ** 2, *shape[2:])
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    upstream = rand(*want.shape, device=device, seed=3)
    for g, r in zip(torch.autograd.grad(got, (present, previous), upstream),
                    torch.autograd.grad(want, (present, previous), upstream)):
        torch.testing.assert_close(g, r, rtol=1e-5, atol=1e-5)


def test_matching_costs_follow_their_definition():
    torch.manual_seed(0)
    present, previous = torch.randn(2, 3, 7, 6), torch.randn(2, 3, 7, 6)
    costs = matching_costs(present, previous, 2)
    assert costs.shape == (2, 25, 7, 6)
    padded = torch.nn.functional.pad(previous, (2, 2, 2, 2), mode="replicate")
    for di, dj, i, j in [(-2, -2, 0, 0), (1, -1, 3, 2), (2, 2, 6, 5), (0, 0, 4, 4), (-1, 2, 1, 5)]:
        n = (di + 2) * 5 + (dj + 2)
        other = padded[:, :, i + di + 2, j + dj + 2]  # previous at (i + di, j + dj), the edge continuing
        assert torch.allclose(costs[:, n, i, j], -(present[:, :, i, j] - other).abs().mean(1))
    # the edge continues: at the corner the shift (-2, -2) compares with previous[0, 0]
    assert torch.allclose(costs[:, 0, 0, 0], -(present[:, :, 0, 0] - previous[:, :, 0, 0]).abs().mean(1))
    assert torch.allclose(matching_costs(present, previous, 0)[:, 0], -(present - previous).abs().mean(1))


def test_matching_costs_find_where_the_content_came_from():
    torch.manual_seed(0)
    r, (di, dj) = 3, (2, -1)
    previous = torch.randn(1, 4, 12, 13)
    present = torch.roll(previous, shifts=(-di, -dj), dims=(-2, -1))  # present[i, j] = previous[i + di, j + dj]
    costs = matching_costs(present, previous, r)
    n = (di + r) * (2 * r + 1) + (dj + r)
    inner = (slice(None), slice(r, 12 - r), slice(r, 13 - r))  # no wrap-around there
    assert torch.allclose(costs[:, n][inner], torch.tensor(0.0), atol=1e-6)
    assert (costs.argmax(1)[inner] == n).all()
    assert (costs[:, n][inner] > costs.amax(1)[inner] - 1e-6).all()
    assert (costs.amax(1) <= 0).all()


def test_matching_costs_of_the_shipped_size_are_the_references_bit_for_bit():
    """The flow forecaster's planes (8 channels, 100 x 100, radius 6): the channels summed in the
    reference's order, so a forecast is the same with either."""
    present, previous = rand(2, 8, 100, 100, seed=6), rand(2, 8, 100, 100, seed=7)
    assert torch.equal(matching_costs(present, previous, 6), reference.matching_costs(present, previous, 6))


def test_matching_costs_non_contiguous(device):
    base_p, base_q = rand(2, 4, 9, 7, device=device, seed=8), rand(2, 4, 9, 7, device=device, seed=9)
    present = base_p.transpose(2, 3).contiguous().transpose(2, 3)
    previous = base_q[:, :, :, :].permute(0, 1, 3, 2).contiguous().permute(0, 1, 3, 2)
    assert not present.is_contiguous() and not previous.is_contiguous()
    torch.testing.assert_close(matching_costs(present, previous, 3), reference.matching_costs(base_p, base_q, 3))


@pytest.mark.parametrize("shape", [(0, 3, 5, 4), (2, 3, 0, 4), (2, 3, 5, 0)])
def test_matching_costs_of_empty_planes_are_empty(device, shape):
    present = rand(*shape, device=device).requires_grad_()
    previous = rand(*shape, device=device).requires_grad_()
    costs = matching_costs(present, previous, 2)
    assert costs.shape == (shape[0], 25, *shape[2:])
    grads = torch.autograd.grad(costs.sum(), (present, previous))
    assert all(g.shape == present.shape for g in grads)


def test_a_tie_has_the_subgradient_zero(device):
    """Where present equals the shifted previous, abs has no slope: no gradient from that shift."""
    present = torch.ones(1, 1, 1, 1, device=device, requires_grad=True)
    previous = torch.ones(1, 1, 1, 1, device=device, requires_grad=True)
    grads = torch.autograd.grad(matching_costs(present, previous, 1).sum(), (present, previous))
    assert all(float(g.abs().sum()) == 0.0 for g in grads)


def test_matching_costs_gradcheck_float64():
    present = rand(2, 3, 5, 4, dtype=torch.float64, seed=10).requires_grad_()
    previous = rand(2, 3, 5, 4, dtype=torch.float64, seed=11).requires_grad_()
    assert torch.autograd.gradcheck(lambda p, q: matching_costs(p, q, 2), (present, previous))
    assert torch.autograd.gradcheck(lambda p, q: matching_costs(p, q, 4), (present[:, :, :1], previous[:, :, :1]))


def test_opcheck_matching_costs(device):
    present = rand(2, 3, 6, 5, device=device, seed=12).requires_grad_()
    previous = rand(2, 3, 6, 5, device=device, seed=13).requires_grad_()
    torch.library.opcheck(torch.ops.t3fast.matching_costs.default, (present, previous, 2))
    grad = rand(2, 25, 6, 5, device=device, seed=14)
    torch.library.opcheck(torch.ops.t3fast.matching_costs_backward.default,
                          (grad, present.detach(), previous.detach(), 2))


def test_double_backward_is_refused_naming_the_reference():
    present = rand(1, 2, 4, 4, dtype=torch.float64).requires_grad_()
    previous = rand(1, 2, 4, 4, dtype=torch.float64, seed=1).requires_grad_()
    (grad,) = torch.autograd.grad(matching_costs(present, previous, 1).pow(2).sum(), present, create_graph=True)
    with pytest.raises(RuntimeError, match="reference.matching_costs"):
        grad.sum().backward()


@pytest.mark.parametrize("present, previous, radius, message", [
    (torch.zeros(2, 3, 4), torch.zeros(2, 3, 4), 1, r"present must have 4 dims \[B, C, H, W\], got 3 dims"),
    (torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 5, 4), 1, r"previous must have the shape of present \[1, 3, 4, 5\]"),
    (torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 4, 5, dtype=torch.float64), 1,
     "previous must have the dtype of present"),
    (torch.zeros(1, 3, 4, 5, dtype=torch.int32), torch.zeros(1, 3, 4, 5, dtype=torch.int32), 1,
     "present must be float32 or float64 on CPU, got Int"),
    (torch.zeros(1, 0, 4, 5), torch.zeros(1, 0, 4, 5), 1, "present must have at least one channel"),
    (torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 4, 5), -1, r"radius must be in \[0, 64\], got -1"),
    (torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 4, 5), 65, r"radius must be in \[0, 64\], got 65"),
])
def test_bad_input_names_the_problem(present, previous, radius, message):
    with pytest.raises(RuntimeError, match=f"t3fast.matching_costs: {message}"):
        matching_costs(present, previous, radius)


def test_planes_on_two_devices_are_refused_naming_them():
    with pytest.raises(RuntimeError, match=r"t3fast.matching_costs: previous must be on the same device as present "
                                           r"\(cpu\), got meta"):
        matching_costs(torch.zeros(1, 3, 4, 5), torch.zeros(1, 3, 4, 5, device="meta"), 1)


def test_backward_of_a_wrong_gradient_shape_names_it():
    present = previous = torch.zeros(1, 3, 4, 5)
    with pytest.raises(RuntimeError, match=r"matching_costs_backward: grad.shape\[1\] \(the \(2 radius \+ 1\)\^2 "
                                           r"shifts\) must be 9, got 25"):
        torch.ops.t3fast.matching_costs_backward(torch.zeros(1, 25, 4, 5), present, previous, 1)
