"""Fused operators versus their PyTorch references (CPU). Run with
``pytest benchmarks --benchmark-only``; each group is read as a reference/fused ratio."""

from __future__ import annotations

import pytest
import torch
from _peak_memory import peak_memory_mb
from workloads import IMPLS, make_decode_inputs, run_decode

IMPL_NAMES = ["fused", "reference"]


@pytest.mark.parametrize("impl", IMPL_NAMES)
@pytest.mark.parametrize("decoder", ["small", "paper"])
@pytest.mark.parametrize("query", ["grid", "argmax"])
def test_decode_grid(benchmark, query, decoder, impl):
    """Full 200x200x16 grid to logits ("grid") or to uint8 labels ("argmax": the argmax mode
    versus the reference's logits.argmax()), with the peak memory of one call."""
    benchmark.group = f"decode grid {'fwd' if query == 'grid' else 'labels'} {decoder}"
    args = make_decode_inputs(decoder)
    benchmark.extra_info["peak_mb"] = peak_memory_mb(impl, {"decoder": decoder}, query)
    with torch.no_grad():
        benchmark.pedantic(run_decode, args=(impl, args, query), rounds=3, warmup_rounds=1)


@pytest.mark.parametrize("impl", IMPL_NAMES)
@pytest.mark.parametrize("decoder", ["small", "paper"])
def test_decode_points_forward_backward(benchmark, decoder, impl):
    """200k sampled points: forward, then backward to planes, weights and biases."""
    benchmark.group = f"decode 200k pts fwd+bwd {decoder}"
    args = make_decode_inputs(decoder, requires_grad=True)
    planes, weights, biases, _ = args
    params = [*planes, *weights, *biases]

    def step():
        out = run_decode(impl, args, "points:200000")
        return torch.autograd.grad(out, params, torch.ones_like(out))

    benchmark.pedantic(step, rounds=3, warmup_rounds=1)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_axis_pool(benchmark, impl):
    benchmark.group = "axis_pool [2,64,100,100,16]"
    volume = torch.randn(2, 64, 100, 100, 16)
    benchmark.pedantic(IMPLS[impl].axis_pool, args=(volume,), rounds=20, warmup_rounds=2)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_axis_pool_backward(benchmark, impl):
    benchmark.group = "axis_pool fwd+bwd [2,64,100,100,16]"
    volume = torch.randn(2, 64, 100, 100, 16, requires_grad=True)

    def step():
        planes = IMPLS[impl].axis_pool(volume)
        return torch.autograd.grad(planes, volume, [torch.ones_like(p) for p in planes])

    benchmark.pedantic(step, rounds=10, warmup_rounds=2)


def _triplane_planes(requires_grad: bool):
    g = torch.Generator().manual_seed(0)
    shapes = [(1, 64, 100, 100), (1, 64, 100, 16), (1, 64, 100, 16)]
    make = lambda s: torch.randn(*s, generator=g).requires_grad_(requires_grad)  # noqa: E731
    deltas = [make(s) for s in shapes]
    prevs = [make(s) for s in shapes]
    weights = [make((64, 64)) for _ in shapes]
    biases = [make((64,)) for _ in shapes]
    return list(zip(deltas, prevs, weights, biases))


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_delta_fuse(benchmark, impl):
    """The three planes of a [1, 64, ...] triplane at 100x100x16."""
    benchmark.group = "delta_fuse triplane C=64"
    planes = _triplane_planes(False)
    op = IMPLS[impl].delta_fuse
    benchmark.pedantic(lambda: [op(*p) for p in planes], rounds=50, warmup_rounds=5)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_delta_fuse_backward(benchmark, impl):
    benchmark.group = "delta_fuse fwd+bwd triplane C=64"
    planes = _triplane_planes(True)
    op = IMPLS[impl].delta_fuse
    inputs = [t for p in planes for t in p]

    def step():
        outs = [op(*p) for p in planes]
        return torch.autograd.grad(outs, inputs, [torch.ones_like(o) for o in outs])

    benchmark.pedantic(step, rounds=30, warmup_rounds=3)
