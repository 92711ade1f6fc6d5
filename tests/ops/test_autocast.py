"""The ops under autocast: inputs from low-precision layers meet float32 planes and weights."""

from __future__ import annotations

import torch

from t3fast.ops import axis_pool, delta_fuse, reference, triplane_decode

from .test_axis_pool_delta_fuse import rand
from .test_triplane_decode import make_inputs


def test_delta_fuse_runs_as_conv2d(device):
    """Under autocast a Delta from a low-precision layer meets the float32 plane and weight: the
    op casts them as conv2d would (CUDA: to the autocast dtype; CPU, whose kernel is float32
    only: to float32), and the gradients reach the float32 leaves."""
    low = torch.bfloat16
    delta = rand(2, 4, 5, 6, device=device).to(low)
    prev = rand(2, 3, 5, 6, device=device, seed=1).requires_grad_()
    weight = rand(4, 3, device=device, seed=2).requires_grad_()
    bias = rand(4, device=device, seed=3)
    with torch.autocast(device, dtype=low):
        got = delta_fuse(delta, prev, weight, bias)
    dtype = low if device == "cuda" else torch.float32
    assert got.dtype == dtype
    want = reference.delta_fuse(delta.to(dtype), prev.to(dtype), weight.to(dtype), bias.to(dtype))
    torch.testing.assert_close(got, want, rtol=1e-2, atol=1e-2)
    got.float().sum().backward()
    assert prev.grad.dtype == torch.float32 and weight.grad.dtype == torch.float32
    torch.testing.assert_close(weight.grad, prev.detach().sum((0, 2, 3)).expand(4, 3), rtol=2e-2, atol=2e-2)


def test_cpu_kernels_run_in_float32():
    """The CPU kernels have no bfloat16: under CPU autocast the ops compute in float32."""
    volume = rand(2, 3, 5, 4, 6).to(torch.bfloat16)
    planes, weights, biases = make_inputs(2, 4, (5, 6, 3), [8], 1, 5)
    low = [p.to(torch.bfloat16) for p in planes]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        pooled = axis_pool(volume)
        logits = triplane_decode(*low, weights, biases, grid=(4, 4, 2), pe_freqs=1)
    for got, want in zip(pooled, reference.axis_pool(volume.float())):
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, want)
    assert logits.dtype == torch.float32
    want = reference.triplane_decode(*(p.float() for p in low), weights, biases, grid=(4, 4, 2), pe_freqs=1)
    torch.testing.assert_close(logits, want, rtol=1e-4, atol=1e-4)
