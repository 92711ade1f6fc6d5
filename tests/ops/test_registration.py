"""torch.library integration: opcheck, torch.compile, and the build report."""

from __future__ import annotations

import pytest
import torch

import t3fast
from t3fast.ops import axis_pool, delta_fuse, reference, triplane_decode

from .test_triplane_decode import make_inputs, random_points


def _decode_samples(device):
    planes, weights, biases = make_inputs(2, 4, (3, 5, 2), [8], 1, 6, device=device)
    params = [t.requires_grad_() for t in (*planes, *weights, *biases)]
    xy, xz, yz, w0, w1, b0, b1 = params
    points = random_points(2, 9, device)
    yield (xy, xz, yz, [w0, w1], [b0, b1], None, [3, 2, 4], 1, False)
    yield (xy, xz, yz, [w0, w1], [b0, b1], points, None, 1, False)
    yield (xy.detach(), xz.detach(), yz.detach(), [w0.detach(), w1.detach()],
           [b0.detach(), b1.detach()], None, [3, 2, 4], 1, True)
    live = torch.tensor([4, 9], device=device)
    yield (xy.detach(), xz.detach(), yz.detach(), [w0.detach(), w1.detach()],
           [b0.detach(), b1.detach()], points, None, 1, True, live)


def test_opcheck_triplane_decode(device):
    for args in _decode_samples(device):
        torch.library.opcheck(torch.ops.t3fast.triplane_decode.default, args)


def test_opcheck_triplane_decode_backward(device):
    planes, weights, biases = make_inputs(2, 4, (3, 5, 2), [8], 1, 6, device=device)
    grad = torch.randn(2, 3, 2, 4, 6, device=device)
    torch.library.opcheck(torch.ops.t3fast.triplane_decode_backward.default,
                          (grad, *planes, weights, biases, None, [3, 2, 4], 1))


def test_opcheck_axis_pool(device):
    volume = torch.randn(2, 3, 4, 5, 6, device=device, requires_grad=True)
    torch.library.opcheck(torch.ops.t3fast.axis_pool.default, (volume,))
    grads = [torch.randn(2, 3, 4, 5), torch.randn(2, 3, 4, 6), torch.randn(2, 3, 5, 6)]
    torch.library.opcheck(torch.ops.t3fast.axis_pool_backward.default,
                          tuple(g.to(device) for g in grads))


@pytest.mark.parametrize("with_bias", [True, False])
def test_opcheck_delta_fuse(device, with_bias):
    delta = torch.randn(2, 4, 5, 6, device=device, requires_grad=True)
    prev = torch.randn(2, 3, 5, 6, device=device, requires_grad=True)
    weight = torch.randn(4, 3, device=device, requires_grad=True)
    bias = torch.randn(4, device=device, requires_grad=True) if with_bias else None
    torch.library.opcheck(torch.ops.t3fast.delta_fuse.default, (delta, prev, weight, bias))
    torch.library.opcheck(torch.ops.t3fast.delta_fuse_backward.default,
                          (delta.detach(), prev.detach(), weight.detach()))


def test_torch_compile_fullgraph(device):
    """All three ops trace into one graph (fake kernels) and give the eager results."""
    planes, weights, biases = make_inputs(1, 4, (6, 6, 4), [16], 2, 5, device=device)
    volume = torch.randn(1, 4, 6, 6, 4, device=device)
    mix = torch.randn(4, 4, device=device)

    def step(volume, weights, biases):
        xy, xz, yz = axis_pool(volume)
        xy = delta_fuse(xy, xy, mix)
        logits = triplane_decode(xy, xz, yz, weights, biases, grid=(6, 6, 4), pe_freqs=2)
        labels = triplane_decode(xy, xz, yz, weights, biases, grid=(6, 6, 4), pe_freqs=2,
                                 argmax=True)
        return logits.sum(), labels

    torch._dynamo.reset()
    compiled = torch.compile(step, fullgraph=True, backend="aot_eager")
    got = compiled(volume, weights, biases)
    want = step(volume, weights, biases)
    torch.testing.assert_close(got[0], want[0])
    assert torch.equal(got[1], want[1])

    # and it trains through the compiled graph
    params = [w.clone().requires_grad_() for w in weights]
    loss = compiled(volume, params, biases)[0]
    loss.backward()
    ref = [w.clone().requires_grad_() for w in weights]
    xy, xz, yz = reference.axis_pool(volume)
    xy = reference.delta_fuse(xy, xy, mix)
    reference.triplane_decode(xy, xz, yz, ref, biases, grid=(6, 6, 4), pe_freqs=2).sum().backward()
    for a, b in zip(params, ref):
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-4)


def test_build_info_reports_the_build():
    info = t3fast.build_info()
    assert info["cpu"] is True
    assert isinstance(info["cuda"], bool)
    assert (info["cuda_version"] > 0) == info["cuda"]
    assert info["torch_version"].split(".")[:2] == torch.__version__.split("+")[0].split(".")[:2]
    assert hasattr(torch.ops.t3fast, "triplane_decode")
