"""Attention: the explicit einsum path (short sequences on the CPU) and the fused
scaled_dot_product_attention path give the same result, forward and backward."""

from __future__ import annotations

import pytest
import torch

from t3fast.models import attention
from t3fast.models.attention import Attention, explicit_attention
from tests.conftest import DEVICES
from tests.models.test_weight_uses import _OpCount


@pytest.mark.parametrize("queries,keys", [(5, 5), (1, 5), (1, 40), (30, 17), (4, 4)])
def test_explicit_and_fused_paths_agree(queries: int, keys: int, monkeypatch) -> None:
    torch.manual_seed(0)
    layer = Attention(12, 3).double()
    x = torch.randn(7, queries, 12, dtype=torch.float64, requires_grad=True)
    context = torch.randn(7, keys, 12, dtype=torch.float64, requires_grad=True)
    results = []
    for explicit in (True, False):
        monkeypatch.setattr(attention, "explicit_attention", lambda q, k, device, e=explicit: e)
        out = layer(x, context)
        grads = torch.autograd.grad(out.sin().sum(), [x, context, layer.q.weight, layer.k.weight])
        results.append((out, *grads))
    for a, b in zip(*results):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_the_explicit_path_is_for_short_sequences_on_the_cpu() -> None:
    cpu = torch.device("cpu")
    assert explicit_attention(5, 5, cpu) and explicit_attention(1, 500, cpu)
    assert not explicit_attention(500, 500, cpu)
    for device in ("cuda", "meta"):
        assert not explicit_attention(5, 5, torch.device(device))


@pytest.mark.parametrize("device", DEVICES)
def test_device_matches_the_cpu(device: str) -> None:
    torch.manual_seed(0)
    layer = Attention(16, 4)
    x, context = torch.randn(64, 1, 16), torch.randn(64, 5, 16)
    expected = layer(x, context)
    torch.testing.assert_close(layer.to(device)(x.to(device), context.to(device)).cpu(), expected,
                               rtol=1e-4, atol=1e-5)


def _separate_projections(layer: Attention, x: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
    """The attention with its q, k and v projections each its own linear (the reference)."""
    n, tq, d = x.shape
    h = layer.heads
    q = layer.q(x).view(n, tq, h, d // h).transpose(1, 2)
    k, v = (proj(context).view(n, -1, h, d // h).transpose(1, 2) for proj in (layer.k, layer.v))
    out = torch.nn.functional.scaled_dot_product_attention(q, k, v).transpose(1, 2)
    return layer.out(out.reshape(n, tq, d))


@pytest.mark.parametrize("self_attention", [True, False])
def test_projections_of_one_input_run_as_one_gemm(self_attention: bool) -> None:
    """Self-attention projects q, k and v in one GEMM, cross-attention k and v: the values and
    gradients of separate projections (float64), and one GEMM per operand in the backward."""
    torch.manual_seed(0)
    layer = Attention(12, 3).double()
    x = torch.randn(7, 5, 12, dtype=torch.float64, requires_grad=True)
    context = x if self_attention else torch.randn(7, 4, 12, dtype=torch.float64, requires_grad=True)
    inputs = [x] if self_attention else [x, context]
    params = [p for proj in (layer.q, layer.k, layer.v) for p in proj.parameters()]
    want = _separate_projections(layer, x, context)
    want_grads = torch.autograd.grad(want.sin().sum(), [*inputs, *params])
    with _OpCount() as counted:
        got = layer(x, context)
        got_grads = torch.autograd.grad(got.sin().sum(), [*inputs, *params])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    for a, b in zip(got_grads, want_grads):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    # the projections' GEMMs (q-k-v; q and k-v), two each in the backward, and the output's with
    # one (its weights' gradients are not asked for); separate projections made 11 either way
    gemms = 1 if self_attention else 2
    assert counted.ops["addmm"] + counted.ops["mm"] == 3 * gemms + 2, counted.ops
