"""Attention: the explicit einsum path (short sequences on the CPU) and the fused
scaled_dot_product_attention path give the same result, forward and backward."""

from __future__ import annotations

import pytest
import torch

from t3fast.models import attention
from t3fast.models.attention import Attention, explicit_attention
from tests.conftest import DEVICES


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
