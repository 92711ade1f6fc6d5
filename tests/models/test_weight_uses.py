"""weights_per_use: a module used several times, its gradients summed over the uses in one
multi-tensor pass instead of an add per weight and use."""

from __future__ import annotations

from collections import Counter

import pytest
import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode

from t3fast.models.weight_uses import _Aliases, call_with, weights_per_use
from tests.conftest import DEVICES


class _OpCount(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops[func._schema.name.split("::")[-1]] += 1
        return func(*args, **(kwargs or {}))


def _net(device: str, dtype: torch.dtype = torch.float64) -> nn.Module:
    torch.manual_seed(0)
    layers = [m for _ in range(6) for m in (nn.Linear(8, 8), nn.Tanh())]
    return nn.Sequential(*layers, nn.LayerNorm(8)).to(device, dtype)


def _rollout(net: nn.Module, x: torch.Tensor, steps: int, aliased: bool) -> torch.Tensor:
    """``steps`` applications of ``net``, each reading the last output: a rollout."""
    uses = weights_per_use(net, steps) if aliased else [None] * steps
    for weights in uses:
        x = call_with(net, weights, x) + x
    return x.square().sum()


def _grads(net: nn.Module, loss: torch.Tensor) -> list[torch.Tensor]:
    return list(torch.autograd.grad(loss, [w for w in net.parameters() if w.requires_grad]))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("steps", [2, 5])
def test_gradients_equal_autograds_own_sums(device: str, steps: int) -> None:
    net = _net(device)
    x = torch.randn(3, 8, device=device, dtype=torch.float64)
    plain = _grads(net, _rollout(net, x, steps, aliased=False))
    aliased = _grads(net, _rollout(net, x, steps, aliased=True))
    for a, b in zip(aliased, plain):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_gradcheck_in_float64() -> None:
    weight = torch.randn(3, 2, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(2, dtype=torch.float64, requires_grad=True)

    def uses_differently(weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        uses = _Aliases.apply(3, weight, bias)
        return torch.stack([(uses[2 * i].sin() * (i + 1)).sum() + uses[2 * i + 1].exp().sum() * i for i in range(3)])

    assert torch.autograd.gradcheck(uses_differently, (weight, bias))


def test_a_weight_one_use_leaves_out_gets_its_other_uses_gradient() -> None:
    net = nn.Linear(4, 4).double()
    x = torch.randn(2, 4, dtype=torch.float64)
    first, second = weights_per_use(net, 2)
    # the second use reads only the weight: the bias's gradient there is None (zeros)
    loss = call_with(net, first, x).sum() + (x @ second["weight"].t()).sum()
    grad_w, grad_b = torch.autograd.grad(loss, [net.weight, net.bias])
    torch.testing.assert_close(grad_w, 2 * x.sum(0).expand(4, 4))
    torch.testing.assert_close(grad_b, torch.full((4,), 2.0, dtype=torch.float64))


def test_frozen_weights_keep_their_own_and_get_no_gradient() -> None:
    net = _net("cpu")
    for layer in list(net)[:4]:
        layer.requires_grad_(False)
    x = torch.randn(3, 8, dtype=torch.float64)
    uses = weights_per_use(net, 3)
    assert all(name.split(".")[0] not in ("0", "2") for name in uses[0])
    plain = _grads(net, _rollout(net, x, 3, aliased=False))
    aliased = _grads(net, _rollout(net, x, 3, aliased=True))
    for a, b in zip(aliased, plain):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert all(w.grad is None for w in list(net)[0].parameters())


def test_no_aliases_where_they_would_not_help() -> None:
    net = _net("cpu")
    assert weights_per_use(net, 1) == [None]
    assert weights_per_use(net, 0) == []
    with torch.no_grad():
        assert weights_per_use(net, 4) == [None] * 4
    assert weights_per_use(nn.Tanh(), 3) == [None] * 3
    assert weights_per_use(_net("cpu").requires_grad_(False), 3) == [None] * 3


def test_uses_read_the_modules_values() -> None:
    net = _net("cpu")
    x = torch.randn(3, 8, dtype=torch.float64)
    for weights in weights_per_use(net, 3):
        torch.testing.assert_close(call_with(net, weights, x), net(x), rtol=0, atol=0)


@pytest.mark.parametrize("device", DEVICES)
def test_backward_adds_no_gradient_per_weight_and_use(device: str) -> None:
    """Plain autograd sums 13 weights' gradients over 4 uses with 3 adds each; the aliases sum
    them with 3 multi-tensor adds, whatever the number of weights."""
    net = _net(device, torch.float32)
    x = torch.randn(3, 8, device=device)
    counts = {}
    for aliased in (False, True):
        loss = _rollout(net, x, 4, aliased)
        with _OpCount() as count:
            loss.backward()
        counts[aliased] = count.ops
    weights = len(list(net.parameters()))
    assert counts[False]["add"] - counts[True]["add"] >= 3 * weights
    assert counts[True]["_foreach_add"] + counts[True]["_foreach_add_"] == 3


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_cuda_sums_take_the_multi_tensor_kernels() -> None:
    """On a GPU the uses' gradients share their layouts, so the sums take the fused multi-tensor
    path: far fewer kernels than an add per weight and use."""
    net = _net("cuda", torch.float32)
    x = torch.randn(3, 8, device="cuda")
    kernels = {}
    for aliased in (False, True):
        for _ in range(2):  # the second run, after any lazy initialisation
            loss = _rollout(net, x, 6, aliased)
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
                loss.backward()
                torch.cuda.synchronize()
        kernels[aliased] = sum(e.count for e in prof.key_averages() if e.device_type == torch.autograd.DeviceType.CUDA)
    weights = len(list(net.parameters()))
    assert kernels[False] - kernels[True] >= 4 * weights, kernels


def test_under_autocast_each_weight_is_cast_once() -> None:
    """Autocast caches the cast of a leaf weight, not of an alias: the aliases are of weights cast
    once, so autocast adds no cast per use, and the backward no add per weight and use."""
    net = _net("cpu", torch.float32)
    x = torch.randn(3, 8)
    counts, grads = {}, {}
    for aliased in (False, True):
        with _OpCount() as count:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                loss = _rollout(net, x, 4, aliased)
            grads[aliased] = _grads(net, loss.float())
        counts[aliased] = count.ops
    linears = 2 * 6  # weight and bias of each Linear
    assert counts[True]["_to_copy"] <= counts[False]["_to_copy"], (counts[True]["_to_copy"], counts[False]["_to_copy"])
    assert counts[False]["add"] - counts[True]["add"] >= 3 * linears
    for a, b in zip(grads[True], grads[False]):  # bfloat16 sums in another order: a few roundings apart
        assert (a - b).norm() <= 0.03 * b.norm(), ((a - b).norm(), b.norm())
