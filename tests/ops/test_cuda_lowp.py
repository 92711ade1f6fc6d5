"""float16 / bfloat16 on CUDA: every op against the float32 reference.

The inputs are drawn in float32 and rounded to the low-precision dtype once; the reference
runs in float32 on exactly those rounded values. The kernels accumulate in float32 and round
only their results, so the expected difference is the final rounding (half an ulp:
2^-11 relative for float16, 2^-8 for bfloat16) plus float32 summation-order noise. The
tolerances below are about four times that rounding, relative to each tensor's largest
magnitude for the gradients (which are long sums).
"""

from __future__ import annotations

import pytest
import torch

from tests.conftest import HAS_CUDA

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA build of t3fast and a GPU"),
]

# dtype -> relative tolerance (about 4 x the final rounding)
TOLERANCE = {torch.float16: 2e-3, torch.bfloat16: 1.6e-2}
LOWP = list(TOLERANCE)


def lowp_pair(t: torch.Tensor, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``t`` rounded to ``dtype`` on the GPU, and the same values in float32."""
    low = t.to("cuda", dtype)
    return low, low.float()


def assert_close_lowp(actual: torch.Tensor, expected: torch.Tensor, dtype: torch.dtype) -> None:
    """Elementwise ``|a - e| <= tol * |e| + tol * max|e|``."""
    assert actual.dtype == dtype
    tol = TOLERANCE[dtype]
    scale = expected.abs().max().item() if expected.numel() else 0.0
    torch.testing.assert_close(actual.float(), expected, rtol=tol, atol=tol * scale + 1e-6)


def decoder(dtype, channels=8, sizes=(20, 18, 8), hidden=(64, 64), pe_freqs=6, classes=18, batch=2, seed=0):
    """Low-precision and float32 copies of planes, weights and biases."""
    g = torch.Generator().manual_seed(seed)
    px, py, pz = sizes
    planes = [torch.randn(batch, channels, *s, generator=g) for s in ((px, py), (px, pz), (py, pz))]
    widths = [channels + 6 * pe_freqs, *hidden, classes]
    weights = [torch.randn(o, i, generator=g) * 1.5 / i**0.5 for i, o in zip(widths, widths[1:])]
    biases = [torch.randn(o, generator=g) * 0.1 for o in widths[1:]]
    low, ref = [], []
    for group in (planes, weights, biases):
        pairs = [lowp_pair(t, dtype) for t in group]
        low.append([p[0] for p in pairs])
        ref.append([p[1] for p in pairs])
    return low, ref


def points_pair(dtype, batch=2, n=3000, seed=1):
    g = torch.Generator().manual_seed(seed)
    return lowp_pair(torch.rand(batch, n, 3, generator=g) * 2.4 - 1.2, dtype)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("hidden", [(64, 64), (256,), (32, 128, 512)])
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_forward(dtype, hidden, mode):
    from t3fast.ops import reference, triplane_decode

    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=hidden)
    if mode == "grid":
        query, query32 = {"grid": (40, 36, 16)}, {"grid": (40, 36, 16)}
    else:
        pts, pts32 = points_pair(dtype)
        query, query32 = {"points": pts}, {"points": pts32}
    got = triplane_decode(*planes, weights, biases, **query)
    want = reference.triplane_decode(*planes32, weights32, biases32, **query32)
    assert_close_lowp(got, want, dtype)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_argmax_is_argmax_of_logits(dtype, mode):
    """The labels are the first maximum of the logits the same kernel writes (exactly)."""
    from t3fast.ops import triplane_decode

    (planes, weights, biases), _ = decoder(dtype)
    query = {"grid": (30, 30, 16)} if mode == "grid" else {"points": points_pair(dtype)[0]}
    logits = triplane_decode(*planes, weights, biases, **query)
    labels = triplane_decode(*planes, weights, biases, argmax=True, **query)
    assert labels.dtype == torch.uint8
    assert torch.equal(labels.long(), logits.argmax(-1))


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_backward(dtype, mode):
    from t3fast.ops import reference, triplane_decode

    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=(64, 32))
    params = [t.requires_grad_() for t in (*planes, *weights, *biases)]
    params32 = [t.requires_grad_() for t in (*planes32, *weights32, *biases32)]
    if mode == "grid":
        query, query32 = {"grid": (24, 20, 8)}, {"grid": (24, 20, 8)}
    else:
        pts, pts32 = points_pair(dtype)
        query, query32 = {"points": pts}, {"points": pts32}
    n = len(weights)
    out = triplane_decode(*params[:3], params[3 : 3 + n], params[3 + n :], **query)
    out32 = reference.triplane_decode(*params32[:3], params32[3 : 3 + n], params32[3 + n :], **query32)
    g = torch.Generator().manual_seed(5)
    upstream, upstream32 = lowp_pair(torch.randn(out.shape, generator=g), dtype)
    got = torch.autograd.grad(out, params, upstream)
    want = torch.autograd.grad(out32, params32, upstream32)
    for a, e in zip(got, want):
        assert_close_lowp(a, e, dtype)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("shape", [(2, 8, 100, 100, 16), (1, 3, 7, 5, 300), (3, 2, 1, 9, 4)])
def test_axis_pool_forward_backward(dtype, shape):
    from t3fast.ops import axis_pool, reference

    g = torch.Generator().manual_seed(0)
    volume, volume32 = lowp_pair(torch.randn(*shape, generator=g), dtype)
    volume.requires_grad_()
    volume32.requires_grad_()
    got = axis_pool(volume)
    want = reference.axis_pool(volume32)
    for a, e in zip(got, want):
        assert_close_lowp(a, e, dtype)
    upstream = [lowp_pair(torch.randn(e.shape, generator=g), dtype) for e in want]
    (grad,) = torch.autograd.grad(got, volume, [u[0] for u in upstream])
    (grad32,) = torch.autograd.grad(want, volume32, [u[1] for u in upstream])
    assert_close_lowp(grad, grad32, dtype)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize(("c_out", "c_in"), [(8, 8), (16, 40), (3, 1)])
@pytest.mark.parametrize("with_bias", [True, False])
def test_delta_fuse_forward_backward(dtype, c_out, c_in, with_bias):
    from t3fast.ops import delta_fuse, reference

    g = torch.Generator().manual_seed(0)
    delta, delta32 = lowp_pair(torch.randn(2, c_out, 37, 29, generator=g), dtype)
    prev, prev32 = lowp_pair(torch.randn(2, c_in, 37, 29, generator=g), dtype)
    weight, weight32 = lowp_pair(torch.randn(c_out, c_in, generator=g) / c_in**0.5, dtype)
    bias, bias32 = lowp_pair(torch.randn(c_out, generator=g), dtype)
    inputs = [delta, prev, weight] + ([bias] if with_bias else [])
    inputs32 = [delta32, prev32, weight32] + ([bias32] if with_bias else [])
    for t in (*inputs, *inputs32):
        t.requires_grad_()
    got = delta_fuse(*inputs)
    want = reference.delta_fuse(*inputs32)
    assert_close_lowp(got, want, dtype)
    upstream, upstream32 = lowp_pair(torch.randn(want.shape, generator=g), dtype)
    grads = torch.autograd.grad(got, inputs, upstream)
    grads32 = torch.autograd.grad(want, inputs32, upstream32)
    for a, e in zip(grads, grads32):
        assert_close_lowp(a, e, dtype)
