"""axis_pool and delta_fuse: parity with the references, forward and backward."""

from __future__ import annotations

import pytest
import torch

from t3fast.ops import axis_pool, delta_fuse, reference


def rand(*shape, device="cpu", dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=dtype).to(device)


@pytest.mark.parametrize("shape", [(0, 3, 4, 5, 6), (1, 1, 1, 1, 1), (3, 5, 7, 5, 3),
                                   (2, 16, 20, 20, 8)])
def test_axis_pool_matches_reference(device, shape):
    volume = rand(*shape, device=device).requires_grad_()
    got = axis_pool(volume)
    want = reference.axis_pool(volume)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-5)
    upstream = [rand(*w.shape, device=device, seed=i + 1) for i, w in enumerate(want)]
    (g_got,) = torch.autograd.grad(got, volume, upstream)
    (g_want,) = torch.autograd.grad(want, volume, upstream)
    torch.testing.assert_close(g_got, g_want, rtol=1e-5, atol=1e-6)


def test_axis_pool_non_contiguous(device):
    base = rand(2, 6, 5, 4, 3, device=device)
    volume = base.transpose(1, 4).contiguous().transpose(1, 4)
    assert not volume.is_contiguous()
    for g, w in zip(axis_pool(volume), reference.axis_pool(base)):
        torch.testing.assert_close(g, w, rtol=1e-5, atol=1e-6)


def test_axis_pool_gradcheck_float64():
    volume = rand(2, 2, 3, 4, 2, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(axis_pool, (volume,))


@pytest.mark.parametrize("with_bias", [True, False])
@pytest.mark.parametrize("shape", [(0, 4, 3, 5, 3), (1, 4, 3, 5, 3), (3, 8, 6, 33, 17),
                                   (2, 16, 16, 40, 30)])
def test_delta_fuse_matches_reference(device, shape, with_bias):
    batch, c_out, c_in, h, w = shape
    delta = rand(batch, c_out, h, w, device=device, seed=1).requires_grad_()
    prev = rand(batch, c_in, h, w, device=device, seed=2).requires_grad_()
    weight = rand(c_out, c_in, device=device, seed=3).requires_grad_()
    bias = rand(c_out, device=device, seed=4).requires_grad_() if with_bias else None
    inputs = [t for t in (delta, prev, weight, bias) if t is not None]
    got = delta_fuse(delta, prev, weight, bias)
    want = reference.delta_fuse(delta, prev, weight, bias)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    upstream = rand(*want.shape, device=device, seed=5)
    for g, r in zip(torch.autograd.grad(got, inputs, upstream),
                    torch.autograd.grad(want, inputs, upstream)):
        torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-4)


def test_delta_fuse_non_contiguous(device):
    delta = rand(2, 5, 7, 6, device=device, seed=1)
    prev = rand(2, 4, 7, 6, device=device, seed=2)
    weight = rand(4, 5, device=device, seed=3).t()  # [5, 4], transposed storage
    bias = rand(10, device=device, seed=4)[::2]
    delta_nc = delta.transpose(2, 3).contiguous().transpose(2, 3)
    prev_nc = prev.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    assert not (delta_nc.is_contiguous() or prev_nc.is_contiguous() or weight.is_contiguous())
    got = delta_fuse(delta_nc, prev_nc, weight, bias)
    torch.testing.assert_close(got, reference.delta_fuse(delta, prev, weight, bias),
                               rtol=1e-5, atol=1e-5)


def test_delta_fuse_gradcheck_float64():
    args = [rand(2, 3, 4, 5, dtype=torch.float64, seed=1), rand(2, 2, 4, 5, dtype=torch.float64,
            seed=2), rand(3, 2, dtype=torch.float64, seed=3), rand(3, dtype=torch.float64, seed=4)]
    assert torch.autograd.gradcheck(delta_fuse, [a.requires_grad_() for a in args])


def test_axis_pool_double_backward_float64():
    """Second-order gradients are exact, not the zero of an op without an autograd formula."""
    volume = rand(2, 2, 3, 4, 2, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradgradcheck(axis_pool, (volume,))
    # a gradient penalty through the pool: d/dv sum(grad_v(sum(pool(v)^2))^2), as the reference
    got, want = [], []
    for f, out in ((axis_pool, got), (reference.axis_pool, want)):
        (g,) = torch.autograd.grad(sum((p**2).sum() for p in f(volume)), volume, create_graph=True)
        out.append(torch.autograd.grad((g**2).sum(), volume)[0])
    torch.testing.assert_close(got[0], want[0])
    assert got[0].abs().sum() > 0


@pytest.mark.parametrize("with_bias", [True, False])
def test_delta_fuse_double_backward_float64(with_bias):
    args = [rand(2, 3, 4, 5, dtype=torch.float64, seed=1), rand(2, 2, 4, 5, dtype=torch.float64, seed=2),
            rand(3, 2, dtype=torch.float64, seed=3), rand(3, dtype=torch.float64, seed=4) if with_bias else None]
    inputs = [a.requires_grad_() for a in args if a is not None]
    assert torch.autograd.gradgradcheck(lambda *t: delta_fuse(*t, *([None] * (4 - len(t)))), inputs)
    got, want = [], []
    for f, out in ((delta_fuse, got), (reference.delta_fuse, want)):
        grads = torch.autograd.grad((f(*args) ** 2).sum(), inputs, create_graph=True)
        out.extend(torch.autograd.grad(sum((g**2).sum() for g in grads), inputs))
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w)
