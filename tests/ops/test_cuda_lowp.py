"""float16 / bfloat16 / TF32 / autocast on CUDA: every op against the float32 reference.

The inputs are drawn in float32 and rounded to the low-precision dtype once; the reference
runs in float32 on exactly those rounded values. axis_pool and delta_fuse accumulate in float32
and round only their results, so the expected difference is the final rounding (half an ulp:
2^-11 relative for float16, 2^-8 for bfloat16) plus float32 summation-order noise.
triplane_decode runs its MLP on tensor cores in the low precision, rounding every hidden
layer's output as torch's linear in that dtype does: it is compared with
``tests.ops.lowp_reference.rounded_decode``, the float32 reference with the same roundings, so
the same difference is expected. The tolerances below are about four times that rounding,
relative to each tensor's largest magnitude. Gradients are compared with upstream gradients that
are zero at the points near a ReLU kink (``kink_free_upstream``), where the exact gradient
jumps and two correct computations may disagree by a hidden unit's whole contribution.
"""

from __future__ import annotations

import pytest
import torch

from tests.conftest import HAS_CUDA
from tests.ops.lowp_reference import kink_free_upstream, rounded_decode

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA build of t3fast and a GPU"),
]

# dtype -> relative tolerance (about 4 x the final rounding)
TOLERANCE = {torch.float16: 2e-3, torch.bfloat16: 1.6e-2}
LOWP = list(TOLERANCE)
# dtype -> distance from a ReLU kink, relative to the layer's RMS pre-activation, within which
# a point's gradient is not compared: well above a rounding of one hidden activation
KINK_MARGIN = {torch.float16: 2e-3, torch.bfloat16: 1e-2, torch.float32: 1e-4}


def lowp_pair(t: torch.Tensor, dtype: torch.dtype, device: str = "cuda") -> tuple[torch.Tensor, torch.Tensor]:
    """``t`` rounded to ``dtype`` on ``device``, and the same values in float32."""
    low = t.to(device, dtype)
    return low, low.float()


def assert_close_lowp(actual: torch.Tensor, expected: torch.Tensor, dtype: torch.dtype) -> None:
    """Elementwise ``|a - e| <= tol * |e| + tol * max|e|``."""
    assert actual.dtype == dtype
    tol = TOLERANCE[dtype]
    scale = expected.abs().max().item() if expected.numel() else 0.0
    torch.testing.assert_close(actual.float(), expected, rtol=tol, atol=tol * scale + 1e-6)


def decoder(dtype, channels=8, sizes=(20, 18, 8), hidden=(64, 64), pe_freqs=6, classes=18, batch=2, seed=0,
            device="cuda"):
    """Low-precision and float32 copies of planes, weights and biases."""
    g = torch.Generator().manual_seed(seed)
    px, py, pz = sizes
    planes = [torch.randn(batch, channels, *s, generator=g) for s in ((px, py), (px, pz), (py, pz))]
    widths = [channels + 6 * pe_freqs, *hidden, classes]
    weights = [torch.randn(o, i, generator=g) * 1.5 / i**0.5 for i, o in zip(widths, widths[1:])]
    biases = [torch.randn(o, generator=g) * 0.1 for o in widths[1:]]
    low, ref = [], []
    for group in (planes, weights, biases):
        pairs = [lowp_pair(t, dtype, device) for t in group]
        low.append([p[0] for p in pairs])
        ref.append([p[1] for p in pairs])
    return low, ref


def points_pair(dtype, batch=2, n=3000, seed=1, device="cuda"):
    g = torch.Generator().manual_seed(seed)
    return lowp_pair(torch.rand(batch, n, 3, generator=g) * 2.4 - 1.2, dtype, device)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("hidden", [(64, 64), (256,), (32, 128, 512)])
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_forward(dtype, hidden, mode):
    from t3fast.ops import triplane_decode

    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=hidden)
    if mode == "grid":
        query, query32 = {"grid": (40, 36, 16)}, {"grid": (40, 36, 16)}
    else:
        pts, pts32 = points_pair(dtype)
        query, query32 = {"points": pts}, {"points": pts32}
    got = triplane_decode(*planes, weights, biases, **query)
    want = rounded_decode(*planes32, weights32, biases32, dtype=dtype, **query32)
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


def decode_gradients(op, planes, weights, biases, query, upstream):
    """Gradients of ``op``'s logits (planes, weights, biases) for ``upstream``."""
    params = [t.detach().requires_grad_() for t in (*planes, *weights, *biases)]
    n = len(weights)
    out = op(*params[:3], params[3 : 3 + n], params[3 + n :], **query)
    return torch.autograd.grad(out, params, upstream)


def backward_case(dtype, mode, device="cuda"):
    """Inputs of the backward comparison: (low, float32) planes, weights, biases, queries, and
    (low, float32) upstream gradients zeroed near the ReLU kinks of the rounded reference."""
    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=(64, 32), device=device)
    if mode == "grid":
        query, query32 = {"grid": (24, 20, 8)}, {"grid": (24, 20, 8)}
    else:
        pts, pts32 = points_pair(dtype, device=device)
        query, query32 = {"points": pts}, {"points": pts32}
    preacts = []
    out32 = rounded_decode(*planes32, weights32, biases32, dtype=dtype, preacts=preacts, **query32)
    g = torch.Generator().manual_seed(5)
    upstream32 = torch.randn(out32.shape, generator=g).to(device, dtype).float()
    upstream32 = kink_free_upstream(upstream32, preacts, KINK_MARGIN[dtype])
    low = (planes, weights, biases, query, upstream32.to(dtype))
    ref = (planes32, weights32, biases32, query32, upstream32)
    return low, ref


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_backward(dtype, mode):
    from t3fast.ops import triplane_decode

    low, ref = backward_case(dtype, mode)
    got = decode_gradients(triplane_decode, *low)
    want = decode_gradients(lambda *a, **q: rounded_decode(*a, dtype=dtype, **q), *ref)
    for a, e in zip(got, want):
        assert_close_lowp(a, e, dtype)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_backward_without_reduced_precision_reductions(dtype, mode, monkeypatch):
    """As :func:`test_triplane_decode_backward`, with cuBLAS kept from reducing partial sums in
    the low precision (PyTorch allows it by default). The backward's GEMMs are cuBLAS's, and its
    default is what the emulator cannot show (its GEMMs are the CPU's, which pass this float16
    grid case with these inputs): a pass here and a failure there places a backward error in
    those reductions."""
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_fp16_reduced_precision_reduction", False)
    monkeypatch.setattr(torch.backends.cuda.matmul, "allow_bf16_reduced_precision_reduction", False)
    test_triplane_decode_backward(dtype, mode)


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("mode", ["grid", "argmax", "points"])
def test_triplane_decode_under_autocast_computes_in_autocast_dtype(dtype, mode):
    """float32 inputs under autocast: float32 logits (labels) of an MLP run in the autocast
    dtype, not the float32 results."""
    from t3fast.ops import reference, triplane_decode

    _, (planes, weights, biases) = decoder(dtype)
    query = {"points": points_pair(dtype)[1]} if mode == "points" else {"grid": (40, 36, 16)}
    with torch.autocast("cuda", dtype=dtype):
        got = triplane_decode(*planes, weights, biases, argmax=mode == "argmax", **query)
        logits = triplane_decode(*planes, weights, biases, **query)
    want = rounded_decode(*planes, weights, biases, dtype=dtype, **query)
    exact = reference.triplane_decode(*planes, weights, biases, **query)
    if mode == "argmax":
        assert got.dtype == torch.uint8
        assert torch.equal(got.long(), logits.argmax(-1))
        return
    assert got.dtype == torch.float32
    scale = want.abs().max().item()
    tol = TOLERANCE[dtype]
    torch.testing.assert_close(got, want, rtol=tol, atol=tol * scale)
    # the low precision is visible: far more than float32's rounding away from the exact values
    assert (got - exact).abs().max().item() > 1e-4 * scale


@pytest.mark.parametrize("dtype", LOWP)
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_backward_under_autocast(dtype, mode):
    """The backward of a forward under autocast recomputes in the autocast dtype (the backward
    itself runs outside the autocast region) and returns float32 gradients."""
    from t3fast.ops import triplane_decode

    _, ref = backward_case(dtype, mode)
    planes, weights, biases, query, upstream = ref
    params = [t.detach().requires_grad_() for t in (*planes, *weights, *biases)]
    n = len(weights)
    with torch.autocast("cuda", dtype=dtype):
        out = triplane_decode(*params[:3], params[3 : 3 + n], params[3 + n :], **query)
    got = torch.autograd.grad(out, params, upstream)
    want = decode_gradients(lambda *a, **q: rounded_decode(*a, dtype=dtype, **q), *ref)
    tol = TOLERANCE[dtype]
    for a, e in zip(got, want):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, e, rtol=tol, atol=tol * e.abs().max().item() + 1e-6)


@pytest.mark.parametrize("mode", ["grid", "points"])
def test_triplane_decode_float32_follows_allow_tf32(mode):
    """float32 inputs compute in float32 (to float32's rounding) unless
    torch.backends.cuda.matmul.allow_tf32 is on, then in TF32 (10-bit mantissas)."""
    from t3fast.ops import reference, triplane_decode

    _, (planes, weights, biases) = decoder(torch.float32, hidden=(256, 256))
    query = {"points": points_pair(torch.float32)[1]} if mode == "points" else {"grid": (40, 36, 16)}
    exact = reference.triplane_decode(*(t.double() for t in planes), [w.double() for w in weights],
                                      [b.double() for b in biases],
                                      **({"points": query["points"].double()} if mode == "points" else query))
    scale = exact.abs().max().item()
    previous = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = False
        fp32 = triplane_decode(*planes, weights, biases, **query)
        torch.backends.cuda.matmul.allow_tf32 = True
        tf32 = triplane_decode(*planes, weights, biases, **query)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = previous
    torch.testing.assert_close(fp32.double(), exact, rtol=1e-5, atol=1e-5 * scale)
    # TF32 rounds every operand to 2^-11 relative: about 1e-3 of the largest logit at most here
    torch.testing.assert_close(tf32.double(), exact, rtol=5e-3, atol=5e-3 * scale)
    assert (tf32.double() - exact).abs().max().item() > 1e-5 * scale


def test_triplane_decode_mma_tiles_every_width():
    """Widths that are not multiples of the 16-wide tiles, one class, the widest layers, many
    layers: the tensor-core kernel against the rounded reference."""
    from t3fast.ops import triplane_decode

    for hidden, classes in [((17,), 1), ((130, 7), 3), ((512,), 18), ((48,) * 9, 5)]:
        (planes, weights, biases), (planes32, weights32, biases32) = decoder(
            torch.bfloat16, hidden=hidden, classes=classes, pe_freqs=2)
        got = triplane_decode(*planes, weights, biases, grid=(9, 7, 5), pe_freqs=2)
        want = rounded_decode(*planes32, weights32, biases32, dtype=torch.bfloat16, grid=(9, 7, 5), pe_freqs=2)
        assert_close_lowp(got, want, torch.bfloat16)


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
