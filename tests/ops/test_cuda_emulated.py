"""t3fast's CUDA operators on the CPU, run by the emulator in ``tests/cuda_emulation``.

``torch.ops.t3fast_emu.<op>`` is the CUDA glue and kernels of ``torch.ops.t3fast.<op>``
(precision rules, tilings, workspaces, the backward's chunks), run on CPU tensors. Each test
compares it with the op's CPU kernel, or for the low precisions with the rounded reference
the CUDA tests use, with the CUDA tests' tolerances; the first tests show that the emulator
enforces CUDA's rules. Speed is not shown here (see ``benchmarks/gpu``).
"""

from __future__ import annotations

import math
from contextlib import contextmanager

import pytest
import torch

from t3fast.ops import reference
from tests.cuda_emulation import load, requires_emulator
from tests.ops import test_bev_components as bev_cases
from tests.ops import test_box_fit as box_fit_cases
from tests.ops import test_draw_boxes as draw_cases
from tests.ops.lowp_reference import kink_free_upstream, rounded_decode
from tests.ops.test_cuda_lowp import (
    KINK_MARGIN,
    TOLERANCE,
    assert_close_lowp,
    backward_case,
    decode_gradients,
    decoder,
    lowp_pair,
    points_pair,
)

pytestmark = requires_emulator

# The tiling cases: every point tile of the SIMT kernel (128, 64, 32 points) with each of its
# register tiles (1, 2, 4, 8 points per thread), every warp grid of the tensor-core kernel,
# odd widths, one class, many layers.
WIDTHS = [((64, 64), 18), ((256,), 18), ((32, 128, 512), 18), ((17,), 1), ((130, 7), 3), ((48,) * 9, 5),
          ((40,), 40), ((90,), 70), ((200, 100), 18), ((300, 200), 18)]
GRID = (9, 7, 5)


@pytest.fixture(scope="module")
def emu():
    return load()


@pytest.fixture(scope="module")
def cuda_ops(emu):
    return torch.ops.t3fast_emu


@contextmanager
def cuda_state(autocast: torch.dtype | None = None, tf32: bool = False):
    """CUDA's autocast and TF32 settings, which the glue reads as on a GPU."""
    saved = (torch.is_autocast_enabled("cuda"), torch.get_autocast_dtype("cuda"),
             torch.backends.cuda.matmul.allow_tf32)
    torch.set_autocast_enabled("cuda", autocast is not None)
    if autocast is not None:
        torch.set_autocast_dtype("cuda", autocast)
    torch.backends.cuda.matmul.allow_tf32 = tf32
    try:
        yield
    finally:
        torch.set_autocast_enabled("cuda", saved[0])
        torch.set_autocast_dtype("cuda", saved[1])
        torch.backends.cuda.matmul.allow_tf32 = saved[2]


def decode(cuda_ops, planes, weights, biases, *, grid=None, points=None, pe_freqs=6, argmax=False, live=None,
           autocast=None, tf32=False):
    with cuda_state(autocast, tf32):
        return cuda_ops.triplane_decode(*planes, weights, biases, points, None if grid is None else list(grid),
                                        pe_freqs, argmax, live)


def float64_case(hidden, classes, pe_freqs=2, seed=0):
    _, (planes, weights, biases) = decoder(torch.float32, hidden=hidden, classes=classes, pe_freqs=pe_freqs,
                                           seed=seed, device="cpu")
    return [t.double() for t in planes], [w.double() for w in weights], [b.double() for b in biases]


def float64_decode(planes, weights, biases, **query):
    """The reference on every input (points included) in float64: the exact logits."""
    query = {k: v.double() if isinstance(v, torch.Tensor) else v for k, v in query.items()}
    return reference.triplane_decode(*(t.double() for t in planes), [w.double() for w in weights],
                                     [b.double() for b in biases], **query)


def assert_same(got, want, rtol=0.0, atol_scale=0.0):
    """Equal tensors (nested in tuples / lists), within ``rtol`` and ``atol_scale`` times
    each tensor's largest magnitude."""
    if isinstance(want, (tuple, list)):
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert_same(g, w, rtol, atol_scale)
        return
    assert got.dtype == want.dtype and got.shape == want.shape
    if rtol == 0.0 and atol_scale == 0.0:
        assert torch.equal(got, want)
        return
    scale = want.abs().max().item() if want.numel() else 0.0
    torch.testing.assert_close(got, want, rtol=rtol, atol=atol_scale * scale + 1e-30, equal_nan=True)


# ---------------------------------------------------------------- the emulator itself

def test_emulator_barriers_and_votes_are_real(emu):
    x = torch.randn(3 * 128)
    assert torch.equal(emu.selftest("reverse", x), x.view(3, 128).flip(1).reshape(-1))
    # without the barrier the early threads read shared memory nobody wrote yet
    assert not torch.equal(emu.selftest("racy_reverse", x), x.view(3, 128).flip(1).reshape(-1))
    # a thread reading a lower thread's slot: in order the race is hidden, last to first it
    # shows, and every other block runs that way
    pair = x[:256].view(2, 128)
    shifted = torch.cat([pair[:, :1], pair[:, :-1]], dim=1).reshape(-1)
    assert torch.equal(emu.selftest("shift", x[:256]), shifted)
    for _ in range(2):  # whichever order each block runs in
        assert not torch.equal(emu.selftest("racy_shift", x[:256]), shifted)
    # asynchronous copies land when waited for, not before
    assert torch.equal(emu.selftest("staged_reverse", x), x.view(3, 128).flip(1).reshape(-1))
    assert not torch.equal(emu.selftest("unwaited_reverse", x), x.view(3, 128).flip(1).reshape(-1))
    votes = torch.full((2 * 128,), -1.0)
    votes[200] = 1.0
    # block 0 has no positive input, block 1 one; all 32 lanes of warp 0 passed __syncwarp
    assert emu.selftest("vote", votes)[:2].tolist() == [320.0, 321.0]


@pytest.mark.parametrize("name, message", [
    ("divergent", "divergent barriers"),
    ("overrun", "wrote past the end of its dynamic shared memory"),
    ("misaligned", "not 256-bit aligned"),
    ("misaligned_async_copy", "not aligned to its size"),
    ("unopted_shared_memory", "more than the kernel's limit"),
])
def test_emulator_fails_launches_that_break_cuda_rules(emu, name, message):
    with pytest.raises(RuntimeError, match=message):
        emu.selftest(name, torch.zeros(128))


# ---------------------------------------------------------------- triplane_decode forward

@pytest.mark.parametrize("hidden, classes", WIDTHS)
@pytest.mark.parametrize("mode", ["grid", "points"])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_cuda_cores_forward_is_the_reference(cuda_ops, hidden, classes, mode, dtype, tol):
    """float64 to its rounding; float32 with TF32 off (the SIMT kernel's wide tile of 128-bit
    loads) to float32's, both against the float64 reference."""
    planes, weights, biases = float64_case(hidden, classes)
    points = points_pair(torch.float32, n=500, device="cpu")[1].double()
    query = {"grid": GRID} if mode == "grid" else {"points": points}
    want = reference.triplane_decode(*planes, weights, biases, pe_freqs=2, **query)
    planes, weights, biases = ([t.to(dtype) for t in group] for group in (planes, weights, biases))
    query = {"grid": GRID} if mode == "grid" else {"points": points.to(dtype)}
    got = decode(cuda_ops, planes, weights, biases, pe_freqs=2, **query)
    assert got.dtype == dtype
    torch.testing.assert_close(got.double(), want, rtol=tol, atol=tol * want.abs().max().item())


@pytest.mark.parametrize("mode", ["grid", "points"])
def test_float32_follows_allow_tf32(cuda_ops, mode):
    """As ``test_cuda_lowp.test_triplane_decode_float32_follows_allow_tf32``: float32 to
    float32's rounding, or with allow_tf32 on the tensor cores in TF32."""
    _, (planes, weights, biases) = decoder(torch.float32, hidden=(256, 256), device="cpu")
    points = points_pair(torch.float32, n=300, device="cpu")[1]
    query = {"grid": (10, 9, 4)} if mode == "grid" else {"points": points}
    exact = float64_decode(planes, weights, biases, **query)
    scale = exact.abs().max().item()
    fp32 = decode(cuda_ops, planes, weights, biases, **query)
    tf32 = decode(cuda_ops, planes, weights, biases, tf32=True, **query)
    torch.testing.assert_close(fp32.double(), exact, rtol=1e-5, atol=1e-5 * scale)
    torch.testing.assert_close(tf32.double(), exact, rtol=5e-3, atol=5e-3 * scale)
    assert (tf32.double() - exact).abs().max().item() > 1e-5 * scale


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("hidden, classes", WIDTHS)
def test_tensor_core_forward_is_the_rounded_reference(cuda_ops, dtype, hidden, classes):
    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=hidden, classes=classes,
                                                                         pe_freqs=2, device="cpu")
    got = decode(cuda_ops, planes, weights, biases, grid=GRID, pe_freqs=2)
    want = rounded_decode(*planes32, weights32, biases32, dtype=dtype, grid=GRID, pe_freqs=2)
    assert_close_lowp(got, want, dtype)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_autocast_computes_in_the_autocast_dtype(cuda_ops, dtype, mode):
    """float32 inputs under CUDA autocast: float32 logits of an MLP run in the autocast dtype."""
    _, (planes, weights, biases) = decoder(dtype, device="cpu")
    query = {"points": points_pair(dtype, n=700, device="cpu")[1]} if mode == "points" else {"grid": (12, 9, 4)}
    got = decode(cuda_ops, planes, weights, biases, autocast=dtype, **query)
    want = rounded_decode(*planes, weights, biases, dtype=dtype, **query)
    exact = reference.triplane_decode(*planes, weights, biases, **query)
    assert got.dtype == torch.float32
    scale = want.abs().max().item()
    torch.testing.assert_close(got, want, rtol=TOLERANCE[dtype], atol=TOLERANCE[dtype] * scale)
    assert (got - exact).abs().max().item() > 1e-4 * scale


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_devices_without_tensor_cores_decode_low_precision_on_cuda_cores(emu, cuda_ops, dtype):
    """Below compute capability 8 the glue takes the SIMT kernel for float16 / bfloat16 too: the
    wide tile reads its low-precision weights and accumulates in float32."""
    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=(256,), device="cpu")
    emu.set_compute_capability(7)
    try:
        got = decode(cuda_ops, planes, weights, biases, grid=GRID)
    finally:
        emu.set_compute_capability(9)
    want = reference.triplane_decode(*planes32, weights32, biases32, grid=GRID)
    assert_close_lowp(got, want, dtype)
    # not the tensor-core path, which rounds every hidden layer to the low precision
    mma = decode(cuda_ops, planes, weights, biases, grid=GRID)
    assert not torch.equal(got, mma)


@pytest.mark.parametrize("state", [{}, {"tf32": True}, {"autocast": torch.float16}, {"autocast": torch.bfloat16}])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
@pytest.mark.parametrize("hidden, classes", [((64, 64), 18), ((32, 128, 512), 18), ((130, 7), 3)])
def test_labels_are_the_argmax_of_the_same_kernels_logits(cuda_ops, state, dtype, hidden, classes):
    (planes, weights, biases), _ = decoder(dtype, hidden=hidden, classes=classes, pe_freqs=2, device="cpu")
    logits = decode(cuda_ops, planes, weights, biases, grid=GRID, pe_freqs=2, **state)
    labels = decode(cuda_ops, planes, weights, biases, grid=GRID, pe_freqs=2, argmax=True, **state)
    assert labels.dtype == torch.uint8
    assert torch.equal(labels.long(), logits.argmax(-1))


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_live_decodes_each_windows_first_points(cuda_ops, dtype):
    """Points past a window's live count get label 0; whole dead tiles are skipped."""
    (planes, weights, biases), _ = decoder(dtype, batch=3, device="cpu")
    points = points_pair(dtype, batch=3, n=600, device="cpu")[0]
    full = decode(cuda_ops, planes, weights, biases, points=points, argmax=True)
    live = torch.tensor([600, 0, 131])
    got = decode(cuda_ops, planes, weights, biases, points=points, argmax=True, live=live)
    keep = torch.arange(600) < live[:, None]
    assert torch.equal(got, torch.where(keep, full, torch.zeros_like(full)))


def test_papers_decoder_size(cuda_ops):
    """The papers' decoder (C_f = 64, 6 frequencies, hidden 256 x 4): the widest tilings of
    both kernels, over more than one block of points."""
    _, (planes, weights, biases) = decoder(torch.float32, channels=64, hidden=(256,) * 4, batch=1, device="cpu")
    points = points_pair(torch.float32, batch=1, n=150, device="cpu")[1]
    exact = float64_decode(planes, weights, biases, points=points)
    scale = exact.abs().max().item()
    fp32 = decode(cuda_ops, planes, weights, biases, points=points)
    torch.testing.assert_close(fp32.double(), exact, rtol=1e-5, atol=1e-5 * scale)
    got = decode(cuda_ops, planes, weights, biases, points=points, autocast=torch.bfloat16)
    want = rounded_decode(*planes, weights, biases, dtype=torch.bfloat16, points=points)
    torch.testing.assert_close(got, want, rtol=1.6e-2, atol=1.6e-2 * want.abs().max().item())


def test_wide_inputs_take_smaller_point_tiles(cuda_ops):
    """Inputs 492 wide with 200 outputs: 128 points would not fit an A100's shared memory, so
    16-bit operands take tiles of 64 points and TF32 ones tiles of 32, over several blocks."""
    _, (planes, weights, biases) = decoder(torch.float32, channels=480, hidden=(200,), pe_freqs=2, batch=1,
                                           device="cpu")
    points = points_pair(torch.float32, batch=1, n=200, device="cpu")[1]
    got = decode(cuda_ops, planes, weights, biases, points=points, pe_freqs=2, autocast=torch.bfloat16)
    want = rounded_decode(*planes, weights, biases, dtype=torch.bfloat16, points=points, pe_freqs=2)
    torch.testing.assert_close(got, want, rtol=1.6e-2, atol=1.6e-2 * want.abs().max().item())
    exact = float64_decode(planes, weights, biases, points=points, pe_freqs=2)
    tf32 = decode(cuda_ops, planes, weights, biases, points=points, pe_freqs=2, tf32=True)
    torch.testing.assert_close(tf32.double(), exact, rtol=5e-3, atol=5e-3 * exact.abs().max().item())


def test_empty_query_launches_nothing(cuda_ops):
    (planes, weights, biases), _ = decoder(torch.float32, device="cpu")
    for state in ({}, {"tf32": True}, {"autocast": torch.bfloat16}):
        assert decode(cuda_ops, planes, weights, biases, points=torch.zeros(2, 0, 3), **state).shape == (2, 0, 18)


# ---------------------------------------------------------------- triplane_decode backward

@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("mode", ["grid", "points"])
def test_backward_is_the_cpu_backward(cuda_ops, dtype, tol, mode):
    """The chunked recomputation, its GEMMs and the scatter kernel against the CPU op, away from
    the ReLU kinks (``kink_free_upstream``)."""
    planes, weights, biases = ([t.to(dtype) for t in group] for group in float64_case((64, 32), 18, pe_freqs=6))
    points = points_pair(torch.float32, n=800, device="cpu")[1].to(dtype)
    query = [None, [24, 20, 8]] if mode == "grid" else [points, None]
    preacts = []
    # in the inputs' own dtype rounded_decode rounds nothing: the reference, with its pre-activations
    out = rounded_decode(*planes, weights, biases, dtype=dtype, preacts=preacts,
                         **({"grid": query[1]} if mode == "grid" else {"points": points}))
    upstream = kink_free_upstream(torch.randn(out.shape, dtype=dtype), preacts, KINK_MARGIN[torch.float32])
    got = cuda_ops.triplane_decode_backward(upstream, *planes, weights, biases, *query, 6)
    want = torch.ops.t3fast.triplane_decode_backward(upstream, *planes, weights, biases, *query, 6)
    assert_same(got, want, rtol=tol, atol_scale=tol)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("autocast", [False, True])
def test_low_precision_backward_is_the_rounded_references(cuda_ops, dtype, autocast):
    """The backward in the low precision (its inputs', or autocast's for float32 inputs) against
    the gradients of the rounded reference, away from the ReLU kinks; the inputs of
    ``test_cuda_lowp.test_triplane_decode_backward[grid]``."""
    (planes, weights, biases, _, upstream), ref = backward_case(dtype, "grid", device="cpu")
    planes32, weights32, biases32, _, upstream32 = ref
    want = decode_gradients(lambda *a, **q: rounded_decode(*a, dtype=dtype, **q), *ref)
    if autocast:
        with cuda_state(autocast=dtype):
            got = cuda_ops.triplane_decode_backward(upstream32, *planes32, weights32, biases32, None, [24, 20, 8], 6)
        assert got[0].dtype == torch.float32
    else:
        got = cuda_ops.triplane_decode_backward(upstream, *planes, weights, biases, None, [24, 20, 8], 6)
    flat = [*got[:3], *got[3], *got[4]]
    tol = TOLERANCE[dtype]
    for a, e in zip(flat, want):
        torch.testing.assert_close(a.float(), e, rtol=tol, atol=tol * e.abs().max().item() + 1e-6)


# ---------------------------------------------------------------- the other operators

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
@pytest.mark.parametrize("shape", [(2, 3, 40, 30, 16), (1, 3, 7, 5, 300), (3, 2, 1, 9, 4), (1, 2, 70, 3, 2)])
def test_axis_pool(cuda_ops, dtype, shape):
    """Forward (one pass, and the chunked plan with its workspace for long x) and backward."""
    volume = torch.randn(*shape).to(dtype)
    got = cuda_ops.axis_pool(volume)
    if dtype in TOLERANCE:
        want = reference.axis_pool(volume.float())
        for a, e in zip(got, want):
            assert_close_lowp(a, e, dtype)
    else:
        assert_same(got, torch.ops.t3fast.axis_pool(volume), rtol=1e-6, atol_scale=1e-6)
    grads = [torch.randn(t.shape).to(dtype) for t in got]
    want = torch.ops.t3fast.axis_pool_backward(*(g.float() for g in grads)).to(dtype)
    tol = TOLERANCE.get(dtype, 1e-6)  # the low precisions: one rounding of the sum
    assert_same(cuda_ops.axis_pool_backward(*grads), want, rtol=tol, atol_scale=tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16])
@pytest.mark.parametrize(("c_out", "c_in"), [(8, 8), (16, 40), (3, 1), (64, 64)])
@pytest.mark.parametrize("with_bias", [True, False])
def test_delta_fuse(cuda_ops, dtype, c_out, c_in, with_bias):
    g = torch.Generator().manual_seed(0)
    low = [lowp_pair(t, dtype, "cpu") for t in (torch.randn(2, c_out, 37, 29, generator=g),
                                                torch.randn(2, c_in, 37, 29, generator=g),
                                                torch.randn(c_out, c_in, generator=g) / c_in**0.5,
                                                torch.randn(c_out, generator=g))]
    (delta, delta32), (prev, prev32), (weight, weight32), (bias, bias32) = low
    got = cuda_ops.delta_fuse(delta, prev, weight, bias if with_bias else None)
    want = torch.ops.t3fast.delta_fuse(delta32, prev32, weight32, bias32 if with_bias else None)
    tol = TOLERANCE.get(dtype, 1e-5)
    assert_same(got.float(), want, rtol=tol, atol_scale=tol)
    grad = torch.randn(want.shape, generator=g).to(dtype)
    got = cuda_ops.delta_fuse_backward(grad, prev, weight)
    want = torch.ops.t3fast.delta_fuse_backward(grad.float(), prev32, weight32)
    for a, e in zip(got, want):
        assert_same(a.float(), e, rtol=tol, atol_scale=tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
@pytest.mark.parametrize("shape, radius", [((2, 8, 20, 18), 6), ((1, 3, 7, 5), 2), ((2, 5, 1, 9), 3),
                                           ((1, 4, 6, 1), 4), ((1, 1, 1, 1), 1)])
def test_matching_costs(cuda_ops, dtype, shape, radius):
    """Forward and backward: the channels and shifts summed in the CPU kernel's order, so float32
    and float64 are its results bit for bit; float16 / bfloat16 accumulate in float32 (one
    rounding of the result)."""
    g = torch.Generator().manual_seed(0)
    (present, present32), (previous, previous32) = (lowp_pair(torch.randn(shape, generator=g), dtype, "cpu")
                                                    for _ in range(2))
    grad, grad32 = lowp_pair(torch.randn(shape[0], (2 * radius + 1) ** 2, *shape[2:], generator=g), dtype, "cpu")
    got = cuda_ops.matching_costs(present, previous, radius)
    got_grads = cuda_ops.matching_costs_backward(grad, present, previous, radius)
    if dtype in TOLERANCE:
        want = torch.ops.t3fast.matching_costs(present32, previous32, radius)
        want_grads = torch.ops.t3fast.matching_costs_backward(grad32, present32, previous32, radius)
        for a, e in zip((got, *got_grads), (want, *want_grads)):
            assert_close_lowp(a, e, dtype)
    else:
        assert_same(got, torch.ops.t3fast.matching_costs(present, previous, radius))
        assert_same(got_grads, torch.ops.t3fast.matching_costs_backward(grad, present, previous, radius))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
@pytest.mark.parametrize("shape, groups, residual", [((2, 8, 9, 7, 5), 4, True), ((1, 4, 20000), 2, False),
                                                     ((3, 6, 13), 6, True), ((2, 3, 1), 1, False)])
def test_group_norm_silu(cuda_ops, dtype, shape, groups, residual):
    """Forward and backward against the CPU kernel: chunks of 8,192 values (several per row in
    the second case) summed in float32 (float64 for float64); float16 / bfloat16 inputs computed
    in float32, each result rounded once."""
    g = torch.Generator().manual_seed(0)
    x, w, b = ((torch.randn(s, generator=g) * 2 + 0.5).to(dtype) for s in (shape, shape[1:2], shape[1:2]))
    r = torch.randn(shape, generator=g).to(dtype) if residual else None
    grad = torch.randn(shape, generator=g).to(dtype)

    def wide(t):  # the same values in the precision the kernels compute in
        return t if t is None or t.dtype in (torch.float32, torch.float64) else t.float()

    got = cuda_ops.group_norm_silu(x, w, b, groups, 1e-5, r)
    want = torch.ops.t3fast.group_norm_silu(wide(x), wide(w), wide(b), groups, 1e-5, wide(r))
    assert got[0].dtype == dtype and got[1].dtype == got[2].dtype == want[1].dtype
    got_grads = cuda_ops.group_norm_silu_backward(grad, x, w, b, r, got[1], got[2], groups)
    want_grads = torch.ops.t3fast.group_norm_silu_backward(wide(grad), wide(x), wide(w), wide(b), wide(r),
                                                           want[1], want[2], groups)
    if not residual:
        assert got_grads[3].numel() == 0
        got_grads, want_grads = got_grads[:3], want_grads[:3]
    tol = {torch.float64: 1e-12, torch.float32: 1e-5}.get(dtype)
    for a, e in zip((*got, *got_grads), (*want, *want_grads)):
        if a.dtype == e.dtype:  # the results of float32 / float64, and the statistics
            assert_same(a, e, tol or 1e-5, tol or 1e-5)
        else:
            assert_close_lowp(a, e, dtype)


def test_group_norm_silu_of_a_large_mean(cuda_ops):
    """The float32 sums are of the values minus the group's first one: a mean 5,000 standard
    deviations from zero still gives the CPU kernel's (float64) statistics and output."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 4, 3000, generator=g) * 2 + 1e4
    w, b = torch.randn(4, generator=g), torch.randn(4, generator=g)
    got, want = cuda_ops.group_norm_silu(x, w, b, 2, 1e-5), torch.ops.t3fast.group_norm_silu(x, w, b, 2, 1e-5)
    assert_same(got, want, 1e-4, 1e-4)


@pytest.mark.parametrize("label_dtype", [torch.uint8, torch.int32, torch.int64])
@pytest.mark.parametrize("shape, classes, channels", [((2, 12, 10, 6), 18, 8), ((1, 5, 1, 9), 3, 13),
                                                      ((1, 1, 1, 1), 2, 1)])
def test_label_conv3d(cuda_ops, label_dtype, shape, classes, channels):
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, classes, shape, generator=g).to(label_dtype)
    table = torch.randn(27, classes, channels, generator=g)
    assert_same(cuda_ops.label_conv3d(labels, table), torch.ops.t3fast.label_conv3d(labels, table),
                 rtol=1e-6, atol_scale=1e-6)
    grad = torch.randn(shape[0], channels, *shape[1:], generator=g)
    assert_same(cuda_ops.label_conv3d_backward(grad, labels, classes),
                torch.ops.t3fast.label_conv3d_backward(grad, labels, classes), rtol=1e-5, atol_scale=1e-5)


@pytest.mark.parametrize("shape, density", [((2, 60, 50), 0.05), ((2, 17, 31), 0.5), ((4, 9, 5), 0.8),
                                            ((1, 1, 40), 0.6), ((1, 40, 1), 0.6)])
def test_bev_components(cuda_ops, shape, density):
    mask = bev_cases.random_masks(shape, density)
    assert_same(cuda_ops.bev_components(mask), torch.ops.t3fast.bev_components(mask))


def test_bev_components_of_a_long_spiral(cuda_ops):
    mask = bev_cases.spiral(41)[None]
    labels, count = cuda_ops.bev_components(mask)
    assert count.tolist() == [1] and torch.equal(labels, torch.ops.t3fast.bev_components(mask)[0])


@pytest.mark.parametrize("batch, count, shape, reach", [(2, 1, (60, 50, 16), 26), (2, 30, (60, 50, 16), 26),
                                                        (2, 25, (17, 9, 5), 3), (1, 7, (1, 1, 1), 0)])
def test_draw_boxes(cuda_ops, batch, count, shape, reach):
    volume, boxes, levels, labels = draw_cases.make(batch, count, shape)
    args = (boxes, levels, labels, [-10.0, -10.0], draw_cases.VOXEL, reach)
    assert_same(cuda_ops.draw_boxes(volume, *args), torch.ops.t3fast.draw_boxes(volume, *args))
    # each volume its own levels and labels (shifted per volume, so that they differ)
    each = (boxes, torch.stack([(levels + n) % shape[2] for n in range(batch)]),
            torch.stack([(labels + n) % 18 for n in range(batch)]), [-10.0, -10.0], draw_cases.VOXEL, reach)
    assert_same(cuda_ops.draw_boxes(volume, *each), torch.ops.t3fast.draw_boxes(volume, *each))


@pytest.mark.parametrize("iters, near", [(0, 1), (3, 1), (3, 2)])
def test_box_fit(cuda_ops, iters, near):
    """The fit's samples, Adam steps and IoU against the CPU op (float32 samples: within
    float32's rounding of the steps)."""
    args = box_fit_cases.make(batch=2, agents=4, frames=3, shape=(30, 32))
    got = box_fit_cases.fit(args, iters, near=near, fn=cuda_ops.box_fit)
    want = box_fit_cases.fit(args, iters, near=near, fn=torch.ops.t3fast.box_fit)
    for a, e in zip(got, want):
        torch.testing.assert_close(a, e, rtol=1e-6, atol=1e-6, equal_nan=True)
    assert not math.isnan(got[1][0, 2].item())
