"""The CUDA triplane_decode kernels on the CPU, run by the emulator in ``tests/cuda_emulation``.

The CUDA tests need a GPU; these run the same kernel code (the SIMT forward, the tensor-core
forward in every precision and tiling, the backward's feature and scatter kernels) on any
machine, against the references the CUDA tests use with the same tolerances. The emulator
checks CUDA's rules as it goes (barriers, shared memory bounds and limits, WMMA alignment);
the first tests show that it does.
"""

from __future__ import annotations

import shutil

import pytest
import torch

from t3fast.ops import reference
from tests.ops.lowp_reference import rounded_decode
from tests.ops.test_cuda_lowp import assert_close_lowp, decoder, points_pair

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="needs a host C++ compiler")

# The tiling cases of the CUDA tests: every point tile of the SIMT kernel (128, 64, 32 points)
# and every warp grid of the tensor-core kernel, odd widths, one class, many layers.
WIDTHS = [((64, 64), 18), ((256,), 18), ((32, 128, 512), 18), ((17,), 1), ((130, 7), 3), ((48,) * 9, 5),
          ((40,), 40), ((90,), 70)]
GRID = (9, 7, 5)
PRECISION = {torch.float16: "half", torch.bfloat16: "bfloat16"}


@pytest.fixture(scope="module")
def emu():
    from tests.cuda_emulation import load

    return load()


def run(emu, planes, weights, biases, *, precision, grid=None, points=None, pe_freqs=6, argmax=False,
        live=None):
    out = emu.decode(*planes, weights, biases, points, None if grid is None else list(grid), pe_freqs, argmax,
                     live, precision)
    batch = planes[0].shape[0]
    if grid is not None:
        return out.reshape(batch, *grid, *out.shape[2:])
    return out


def float64_case(hidden, classes, pe_freqs=2, seed=0):
    _, (planes, weights, biases) = decoder(torch.float32, hidden=hidden, classes=classes, pe_freqs=pe_freqs,
                                           seed=seed, device="cpu")
    return [t.double() for t in planes], [w.double() for w in weights], [b.double() for b in biases]


def test_emulator_barriers_and_votes_are_real(emu):
    x = torch.randn(3 * 128)
    assert torch.equal(emu.selftest("reverse", x), x.view(3, 128).flip(1).reshape(-1))
    votes = torch.full((2 * 128,), -1.0)
    votes[200] = 1.0
    # block 0 has no positive input, block 1 one; all 32 lanes of warp 0 passed __syncwarp
    assert emu.selftest("vote", votes)[:2].tolist() == [320.0, 321.0]


@pytest.mark.parametrize("name, message", [
    ("divergent", "divergent barriers"),
    ("overrun", "wrote past the end of its dynamic shared memory"),
    ("misaligned", "not 256-bit aligned"),
    ("unopted_shared_memory", "more than the kernel's limit"),
])
def test_emulator_fails_launches_that_break_cuda_rules(emu, name, message):
    with pytest.raises(RuntimeError, match=message):
        emu.selftest(name, torch.zeros(128))


@pytest.mark.parametrize("hidden, classes", WIDTHS)
@pytest.mark.parametrize("mode", ["grid", "points"])
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_simt_forward_is_the_reference(emu, hidden, classes, mode, dtype, tol):
    """float64 to its rounding; float32 (the wide tile's 128-bit loads) to float32's, against
    the float64 reference."""
    planes, weights, biases = float64_case(hidden, classes)
    points = points_pair(torch.float32, n=500, device="cpu")[1].double()
    query = {"grid": GRID} if mode == "grid" else {"points": points}
    want = reference.triplane_decode(*planes, weights, biases, pe_freqs=2, **query)
    if dtype != torch.float64:
        planes, weights, biases = ([t.to(dtype) for t in group] for group in (planes, weights, biases))
        query = {"grid": GRID} if mode == "grid" else {"points": points.to(dtype)}
    got = run(emu, planes, weights, biases, precision="cuda_cores", pe_freqs=2, **query)
    assert got.dtype == dtype
    torch.testing.assert_close(got.double(), want, rtol=tol, atol=tol * want.abs().max().item())


@pytest.mark.parametrize("mode", ["grid", "points"])
def test_simt_forward_float32_and_tf32(emu, mode):
    """float32 on CUDA cores to float32's rounding; the tensor-core TF32 forward to TF32's
    (the CUDA test ``test_triplane_decode_float32_follows_allow_tf32``'s tolerances)."""
    planes, weights, biases = float64_case((256, 256), 18, pe_freqs=6)
    query = {"grid": (10, 9, 4)} if mode == "grid" else {"points": points_pair(torch.float32, n=300, device="cpu")[1]}
    exact = reference.triplane_decode(*planes, weights, biases,
                                      **({"points": query["points"].double()} if mode == "points" else query))
    scale = exact.abs().max().item()
    f32 = [[t.float() for t in group] for group in (planes, weights, biases)]
    fp32 = run(emu, *f32, precision="cuda_cores", **query)
    tf32 = run(emu, *f32, precision="tf32", **query)
    torch.testing.assert_close(fp32.double(), exact, rtol=1e-5, atol=1e-5 * scale)
    torch.testing.assert_close(tf32.double(), exact, rtol=5e-3, atol=5e-3 * scale)
    assert (tf32.double() - exact).abs().max().item() > 1e-5 * scale


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
@pytest.mark.parametrize("hidden, classes", WIDTHS)
def test_mma_forward_is_the_rounded_reference(emu, dtype, hidden, classes):
    (planes, weights, biases), (planes32, weights32, biases32) = decoder(dtype, hidden=hidden, classes=classes,
                                                                         pe_freqs=2, device="cpu")
    got = run(emu, planes, weights, biases, precision=PRECISION[dtype], grid=GRID, pe_freqs=2)
    want = rounded_decode(*planes32, weights32, biases32, dtype=dtype, grid=GRID, pe_freqs=2)
    assert_close_lowp(got, want, dtype)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_mma_forward_of_float32_inputs_under_autocast(emu, dtype):
    """float32 planes and points, MLP in the autocast dtype, float32 logits."""
    _, (planes, weights, biases) = decoder(torch.float32, hidden=(64, 64), device="cpu")
    points = points_pair(torch.float32, n=700, device="cpu")[1]
    got = run(emu, planes, weights, biases, precision=PRECISION[dtype], points=points)
    want = rounded_decode(*planes, weights, biases, dtype=dtype, points=points)
    assert got.dtype == torch.float32
    tol = {torch.float16: 2e-3, torch.bfloat16: 1.6e-2}[dtype]
    torch.testing.assert_close(got, want, rtol=tol, atol=tol * want.abs().max().item())


@pytest.mark.parametrize("precision, dtype", [("cuda_cores", torch.float32), ("cuda_cores", torch.float64),
                                              ("tf32", torch.float32), ("half", torch.float16),
                                              ("bfloat16", torch.bfloat16), ("bfloat16", torch.float32)])
@pytest.mark.parametrize("hidden, classes", [((64, 64), 18), ((32, 128, 512), 18), ((130, 7), 3)])
def test_labels_are_the_argmax_of_the_same_kernels_logits(emu, precision, dtype, hidden, classes):
    (planes, weights, biases), _ = decoder(dtype, hidden=hidden, classes=classes, pe_freqs=2, device="cpu")
    logits = run(emu, planes, weights, biases, precision=precision, grid=GRID, pe_freqs=2)
    labels = run(emu, planes, weights, biases, precision=precision, grid=GRID, pe_freqs=2, argmax=True)
    assert labels.dtype == torch.uint8
    assert torch.equal(labels.long(), logits.argmax(-1))


@pytest.mark.parametrize("precision, dtype", [("cuda_cores", torch.float32), ("bfloat16", torch.bfloat16)])
def test_live_decodes_each_windows_first_points(emu, precision, dtype):
    """Points past a window's live count get label 0; whole dead tiles are skipped."""
    (planes, weights, biases), _ = decoder(dtype, batch=3, device="cpu")
    points = points_pair(dtype, batch=3, n=600, device="cpu")[0]
    full = run(emu, planes, weights, biases, precision=precision, points=points, argmax=True)
    live = torch.tensor([600, 0, 131])
    got = run(emu, planes, weights, biases, precision=precision, points=points, argmax=True, live=live)
    keep = torch.arange(600) < live[:, None]
    assert torch.equal(got, torch.where(keep, full, torch.zeros_like(full)))


def test_papers_decoder_size(emu):
    """The papers' decoder (C_f = 64, 6 frequencies, hidden 256 x 4): the widest tilings of
    both kernels, over more than one block of points."""
    _, (planes, weights, biases) = decoder(torch.float32, channels=64, hidden=(256,) * 4, batch=1, device="cpu")
    points = points_pair(torch.float32, batch=1, n=150, device="cpu")[1]
    exact = reference.triplane_decode(*(t.double() for t in planes), [w.double() for w in weights],
                                      [b.double() for b in biases], points=points.double())
    scale = exact.abs().max().item()
    fp32 = run(emu, planes, weights, biases, precision="cuda_cores", points=points)
    torch.testing.assert_close(fp32.double(), exact, rtol=1e-5, atol=1e-5 * scale)
    got = run(emu, planes, weights, biases, precision="bfloat16", points=points)
    want = rounded_decode(*planes, weights, biases, dtype=torch.bfloat16, points=points)
    torch.testing.assert_close(got, want, rtol=1.6e-2, atol=1.6e-2 * want.abs().max().item())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_backward_kernels(emu, dtype):
    """The backward's feature kernel is the reference's features, and its scatter kernel the
    transpose of their plane lookups (the reference's autograd)."""
    _, (planes, _, _) = decoder(torch.float32, batch=2, device="cpu")
    planes = [p.to(dtype).requires_grad_() for p in planes]
    points = points_pair(torch.float32, batch=2, n=400, device="cpu")[1].to(dtype)
    want = reference.triplane_features(*planes, points, 6)
    got = emu.features(*(p.detach() for p in planes), points, None, 6)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(got, want.detach().reshape(got.shape), rtol=tol, atol=tol)
    grad = torch.randn(want.shape, dtype=dtype)
    want_grads = torch.autograd.grad(want, planes, grad)
    got_grads = emu.scatter(*(p.detach() for p in planes), points, None, grad.reshape(-1, grad.shape[-1]))
    for g, w in zip(got_grads, want_grads):
        torch.testing.assert_close(g, w, rtol=tol, atol=tol)


def test_empty_query_launches_nothing(emu):
    (planes, weights, biases), _ = decoder(torch.float32, device="cpu")
    points = torch.zeros(2, 0, 3)
    for precision in ("cuda_cores", "tf32", "bfloat16"):
        assert run(emu, planes, weights, biases, precision=precision, points=points).shape == (2, 0, 18)
