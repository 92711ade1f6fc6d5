"""triplane_decode: parity with the reference in every mode, forward and backward."""

from __future__ import annotations

import pytest
import torch

from t3fast.ops import reference, triplane_decode

# (C, plane sizes (X', Y', Z'), MLP hidden widths, pe_freqs)
CONFIGS = [
    (5, (3, 4, 6), [16, 7], 2),  # odd sizes, three layers
    (8, (10, 12, 4), [], 6),  # a single linear layer
    (16, (20, 20, 8), [64, 64], 6),  # the small decoder
    (12, (6, 5, 4), [256], 3),  # wide hidden layer
    (3, (1, 1, 1), [9, 9, 9, 9], 0),  # 1x1 planes, no encoding, deep
]


def make_inputs(batch, channels, sizes, hidden, pe_freqs, classes=11, device="cpu",
                dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)

    def rand(*shape, scale=1.0):
        return (torch.randn(*shape, generator=g, dtype=dtype) * scale).to(device)

    px, py, pz = sizes
    planes = [rand(batch, channels, px, py), rand(batch, channels, px, pz),
              rand(batch, channels, py, pz)]
    widths = [channels + 6 * pe_freqs, *hidden, classes]
    weights = [rand(o, i, scale=1.5 / i**0.5) for i, o in zip(widths[:-1], widths[1:])]
    biases = [rand(o, scale=0.1) for o in widths[1:]]
    return planes, weights, biases


def random_points(batch, n, device="cpu", dtype=torch.float32, seed=1):
    g = torch.Generator().manual_seed(seed)
    # a margin beyond [-1, 1] exercises the border clamping
    return (torch.rand(batch, n, 3, generator=g, dtype=dtype) * 2.4 - 1.2).to(device)


def decode_both(planes, weights, biases, **query):
    fused = triplane_decode(*planes, weights, biases, **query)
    ref = reference.triplane_decode(*planes, weights, biases, **query)
    return fused, ref


@pytest.mark.parametrize("config", CONFIGS)
@pytest.mark.parametrize("batch", [0, 1, 3])
def test_grid_forward_matches_reference(device, config, batch):
    channels, sizes, hidden, freqs = config
    planes, weights, biases = make_inputs(batch, channels, sizes, hidden, freqs, device=device)
    fused, ref = decode_both(planes, weights, biases, grid=(7, 5, 3), pe_freqs=freqs)
    assert fused.shape == (batch, 7, 5, 3, 11)
    torch.testing.assert_close(fused, ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("config", CONFIGS)
@pytest.mark.parametrize("batch", [0, 1, 3])
def test_points_forward_matches_reference(device, config, batch):
    channels, sizes, hidden, freqs = config
    planes, weights, biases = make_inputs(batch, channels, sizes, hidden, freqs, device=device)
    points = random_points(batch, 1500, device=device)  # more than one chunk
    fused, ref = decode_both(planes, weights, biases, points=points, pe_freqs=freqs)
    assert fused.shape == (batch, 1500, 11)
    torch.testing.assert_close(fused, ref, rtol=1e-4, atol=1e-4)


def test_grid_at_occ3d_resolution(device):
    """The production shape: 200 x 200 x 16 voxels from 100 x 100 x 16 planes."""
    planes, weights, biases = make_inputs(1, 8, (100, 100, 16), [32, 32], 6, 18, device=device)
    fused, ref = decode_both(planes, weights, biases, grid=(200, 200, 16))
    torch.testing.assert_close(fused, ref, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("mode", ["grid", "points"])
def test_argmax_matches_reference_argmax(device, mode):
    planes, weights, biases = make_inputs(2, 6, (9, 7, 5), [32], 4, 18, device=device)
    query = {"grid": (11, 9, 5)} if mode == "grid" else {"points": random_points(2, 3000, device)}
    labels = triplane_decode(*planes, weights, biases, pe_freqs=4, argmax=True, **query)
    logits = reference.triplane_decode(*planes, weights, biases, pe_freqs=4, **query)
    assert labels.dtype == torch.uint8
    assert labels.shape == logits.shape[:-1]
    # where the top two logits are not within rounding of each other, the class must agree
    top2 = logits.topk(2, dim=-1).values
    clear = (top2[..., 0] - top2[..., 1]) > 1e-4
    assert clear.float().mean() > 0.99
    assert torch.equal(labels[clear].long(), logits.argmax(-1)[clear])


def test_argmax_first_maximum_on_ties(device):
    """All-equal logits (zero weights) must give class 0, like torch.argmax."""
    planes, weights, biases = make_inputs(1, 4, (3, 3, 3), [8], 1, 5, device=device)
    weights[-1] = torch.zeros_like(weights[-1])
    biases[-1] = torch.zeros_like(biases[-1])
    labels = triplane_decode(*planes, weights, biases, grid=(4, 4, 2), pe_freqs=1, argmax=True)
    assert torch.all(labels == 0)


@pytest.mark.parametrize("mode", ["grid", "points"])
@pytest.mark.parametrize("hidden", [[16, 7], [], [64, 64], [256]])
def test_backward_matches_reference(device, mode, hidden):
    planes, weights, biases = make_inputs(3, 5, (3, 4, 6), hidden, 2, device=device)
    params = [t.requires_grad_() for t in (*planes, *weights, *biases)]
    query = {"grid": (7, 5, 3)} if mode == "grid" else {"points": random_points(3, 1100, device)}
    n = len(weights)

    def grads(fn):
        out = fn(*params[:3], params[3 : 3 + n], params[3 + n :], pe_freqs=2, **query)
        g = torch.Generator().manual_seed(5)
        upstream = torch.randn(out.shape, generator=g).to(device)
        return torch.autograd.grad(out, params, upstream)

    for got, want in zip(grads(triplane_decode), grads(reference.triplane_decode)):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)


def test_non_contiguous_inputs(device):
    planes, weights, biases = make_inputs(2, 6, (5, 4, 3), [16], 2, device=device)
    # channels-last planes, transposed weights, a strided point tensor
    planes_nc = [p.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2) for p in planes]
    weights_nc = [w.t().contiguous().t() for w in weights]
    points = random_points(2, 400, device).repeat(1, 1, 2)[..., ::2]
    for p, q in zip(planes_nc, planes):
        assert not p.is_contiguous() and torch.equal(p, q)
    assert not points.is_contiguous() and not weights_nc[0].is_contiguous()
    for query in ({"grid": (5, 4, 3)}, {"points": points}):
        fused = triplane_decode(*planes_nc, weights_nc, biases, pe_freqs=2, **query)
        ref = reference.triplane_decode(*planes, weights, biases, pe_freqs=2, **query)
        torch.testing.assert_close(fused, ref, rtol=1e-4, atol=1e-4)


def test_empty_queries(device):
    planes, weights, biases = make_inputs(2, 4, (3, 3, 3), [8], 1, device=device)
    points = torch.zeros(2, 0, 3, device=device)
    assert triplane_decode(*planes, weights, biases, points=points, pe_freqs=1).shape == (2, 0, 11)
    out = triplane_decode(*planes, weights, biases, grid=(0, 4, 4), pe_freqs=1, argmax=True)
    assert out.shape == (2, 0, 4, 4) and out.dtype == torch.uint8


@pytest.mark.parametrize("mode", ["grid", "points"])
def test_gradcheck_float64(mode):
    planes, weights, biases = make_inputs(2, 3, (3, 4, 2), [5], 1, 4, dtype=torch.float64)
    params = [t.requires_grad_() for t in (*planes, *weights, *biases)]
    if mode == "grid":
        query = {"grid": (3, 2, 3)}
    else:
        # keep points away from cell centres, where the bilinear weights have kinks
        query = {"points": random_points(2, 7, dtype=torch.float64) * 0.8 + 0.013}

    def fn(xy, xz, yz, w0, w1, b0, b1):
        return triplane_decode(xy, xz, yz, [w0, w1], [b0, b1], pe_freqs=1, **query)

    assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-5)


def test_runs_on_a_chunk_boundary():
    """Exactly one chunk, one chunk + 1 and several chunks give the same rows (up to the
    GEMM's blocking, which depends on the row count)."""
    planes, weights, biases = make_inputs(1, 4, (5, 5, 5), [8], 2)
    points = random_points(1, 3 * 1024 + 1)
    full = triplane_decode(*planes, weights, biases, points=points, pe_freqs=2)
    for n in (1024, 1025, 2048):
        part = triplane_decode(*planes, weights, biases, points=points[:, :n], pe_freqs=2)
        torch.testing.assert_close(part, full[:, :n], rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("mode", ["grid", "points"])
def test_double_backward_raises_instead_of_a_zero_gradient(mode):
    """The fused op has no second-order formula: differentiating its gradient is an error that
    points at the reference (torch's fallback would return a zero gradient with a warning)."""
    planes, weights, biases = make_inputs(1, 4, (3, 5, 2), [8], 1, 6, dtype=torch.float64)
    planes = [p.requires_grad_() for p in planes]
    query = {"grid": (3, 2, 4)} if mode == "grid" else {"points": random_points(1, 9, dtype=torch.float64)}
    (g,) = torch.autograd.grad((triplane_decode(*planes, weights, biases, pe_freqs=1, **query) ** 2).sum(),
                               planes[0], create_graph=True)  # first order with a graph still works
    with pytest.raises(RuntimeError, match="t3fast.triplane_decode: double backward is not supported; "
                                           "use t3fast.ops.reference.triplane_decode"):
        torch.autograd.grad((g**2).sum(), planes[0])
    # the reference has the second-order gradient the fused op refuses to fake, from torch 2.12 on
    # (earlier releases have no double backward of grid_sample, and say so)
    (g,) = torch.autograd.grad((reference.triplane_decode(*planes, weights, biases, pe_freqs=1, **query) ** 2)
                               .sum(), planes[0], create_graph=True)
    if torch.torch_version.TorchVersion(torch.__version__) < (2, 12):
        with pytest.raises(RuntimeError, match="grid_sampler_2d_backward is not implemented"):
            torch.autograd.grad((g**2).sum(), planes[0])
    else:
        assert torch.autograd.grad((g**2).sum(), planes[0])[0].abs().sum() > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_live_decodes_each_elements_first_points_and_labels_the_rest_0(device, dtype):
    """A fixed-size buffer of points filled to a count per element (kept on the device):
    the labels of the counted points are those of a full decode, the others 0; counts clamp
    to [0, N]."""
    planes, weights, biases = make_inputs(5, 6, (9, 7, 5), [32, 16], 2, 11, device=device, dtype=dtype)
    n = 5003  # several CPU chunks and GPU blocks, the last ones partial
    points = random_points(5, n, device, dtype)
    counts = torch.tensor([0, 1, 2049, n + 7, -3], device=device)
    live = torch.stack([counts, torch.zeros_like(counts)], 1)[:, 0]  # not contiguous
    got = triplane_decode(*planes, weights, biases, points=points, pe_freqs=2, argmax=True, live=live)
    full = triplane_decode(*planes, weights, biases, points=points, pe_freqs=2, argmax=True)
    decoded = torch.arange(n, device=device) < counts.clamp(0, n)[:, None]
    assert torch.equal(got, torch.where(decoded, full, torch.zeros_like(full)))
    assert full[decoded].ne(0).any() and full[~decoded].ne(0).any()  # both parts can tell
    want = reference.triplane_decode(*planes, weights, biases, points=points, pe_freqs=2, argmax=True, live=live)
    assert torch.equal(got, want)


def test_live_compiles_into_a_graph(device):
    planes, weights, biases = make_inputs(2, 4, (5, 6, 3), [8], 1, 5, device=device)
    points = random_points(2, 40, device)

    def decode(points, live):
        return triplane_decode(*planes, weights, biases, points=points, pe_freqs=1, argmax=True, live=live)

    live = torch.tensor([17, 40], device=device)
    compiled = torch.compile(decode, fullgraph=True, backend="aot_eager")
    assert torch.equal(compiled(points, live), decode(points, live))
