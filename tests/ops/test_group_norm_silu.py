"""group_norm_silu: parity with the reference forward and backward (with and without a residual,
odd sizes, one group, one value per channel, large means, non-contiguous and empty inputs),
gradcheck, opcheck, autocast, and bad input."""

from __future__ import annotations

import pytest
import torch

from t3fast.ops import group_norm_silu, reference

# (input shape, groups): the encoder's blocks, odd sizes, one group, a group per channel, 2-D
CASES = [((2, 16, 20, 20, 16), 8), ((1, 8, 9, 7, 5), 8), ((2, 6, 13), 3), ((3, 4, 5, 7), 1), ((2, 12, 1), 4),
         ((1, 3, 2, 3), 3), ((4, 6), 2), ((1, 2, 40_000), 2)]


def rand(*shape, device="cpu", dtype=torch.float32, seed=0, scale=1.0, shift=0.0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(*shape, generator=g, dtype=dtype) * scale + shift).to(device)


def inputs(shape, device="cpu", dtype=torch.float32, residual=True, shift=0.5):
    c = shape[1]
    x = rand(*shape, device=device, dtype=dtype, seed=1, scale=3.0, shift=shift)
    w, b = rand(c, device=device, dtype=dtype, seed=2), rand(c, device=device, dtype=dtype, seed=3)
    r = rand(*shape, device=device, dtype=dtype, seed=4) if residual else None
    return x, w, b, r


@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("shape, groups", CASES)
def test_group_norm_silu_matches_the_reference(device, shape, groups, residual):
    x, w, b, r = inputs(shape, device, residual=residual)
    leaves = [t.requires_grad_() for t in (x, w, b, r) if t is not None]
    got = group_norm_silu(x, w, b, groups, 1e-5, r)
    want = reference.group_norm_silu(x, w, b, groups, 1e-5, r)
    assert got.shape == x.shape and got.dtype == x.dtype
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    upstream = rand(*shape, device=device, seed=5)
    for g, e in zip(torch.autograd.grad(got, leaves, upstream), torch.autograd.grad(want, leaves, upstream)):
        scale = e.abs().max().item()
        torch.testing.assert_close(g, e, rtol=1e-4, atol=1e-4 * max(scale, 1.0))


def test_group_norm_silu_is_what_it_says():
    """Per group: (x - mean) / sqrt(biased var + eps), per channel * weight + bias, + residual, silu."""
    x, w, b, r = inputs((2, 6, 5, 4), residual=True)
    x, w, b, r = x.double(), w.double(), b.double(), r.double()
    got = group_norm_silu(x, w, b, 3, 0.1, r)
    groups = x.view(2, 3, -1)
    normed = ((groups - groups.mean(-1, keepdim=True)) / (groups.var(-1, unbiased=False, keepdim=True) + 0.1).sqrt())
    z = normed.view_as(x) * w[:, None, None] + b[:, None, None] + r
    torch.testing.assert_close(got, z * torch.sigmoid(z), rtol=1e-12, atol=1e-12)


def test_a_large_mean_keeps_the_variance(device):
    """The groups' sums are shifted by their first value: a mean 10^4 standard deviations away
    from zero still normalises to float32's rounding of the values themselves."""
    x, w, b, _ = inputs((2, 4, 30, 30), device, residual=False, shift=3e4)
    exact = reference.group_norm_silu(x.double(), w.double(), b.double(), 2, 1e-5)
    got = group_norm_silu(x, w, b, 2, 1e-5)
    assert (got.double() - exact).abs().max().item() < 2e-3  # x's own rounding: 3e4 * 6e-8 / std 3


def test_silu_far_from_zero(device):
    """Large pre-activations: silu(z) = z above, 0 (to float32's range) below; NaN stays NaN."""
    x = torch.tensor([[[-1.0, 1.0]], [[-1.0, 1.0]]], device=device)  # normalises to -1, 1
    w, b = torch.tensor([500.0], device=device), torch.tensor([0.0], device=device)
    got = group_norm_silu(x, w, b, 1, 0.0)
    torch.testing.assert_close(got, torch.tensor([[[0.0, 500.0]], [[0.0, 500.0]]], device=device),
                               atol=1e-6, rtol=1e-6)
    x[0, 0, 0] = float("nan")
    got = group_norm_silu(x, w, b, 1, 0.0)
    assert got[0].isnan().all() and not got[1].isnan().any()


def test_group_norm_silu_non_contiguous(device):
    x, w, b, r = inputs((2, 8, 6, 5), device)
    xt = x.transpose(2, 3).contiguous().transpose(2, 3)
    rt = r.transpose(2, 3).contiguous().transpose(2, 3)
    ws, bs = torch.stack([w, w], 1)[:, 0], torch.stack([b, b], 1)[:, 1]
    assert not (xt.is_contiguous() or rt.is_contiguous() or ws.is_contiguous())
    torch.testing.assert_close(group_norm_silu(xt, ws, bs, 4, 1e-5, rt), reference.group_norm_silu(x, w, b, 4, 1e-5, r))


@pytest.mark.parametrize("shape", [(0, 4, 5), (2, 4, 0), (2, 0, 3)])
def test_empty_inputs_give_empty_outputs(device, shape):
    x, w, b, r = inputs(shape, device)
    leaves = [t.requires_grad_() for t in (x, w, b, r)]
    out = group_norm_silu(x, w, b, 2 if shape[1] else 1, 1e-5, r)
    assert out.shape == x.shape
    grads = torch.autograd.grad(out.sum(), leaves)
    assert [g.shape for g in grads] == [t.shape for t in leaves]
    assert all(float(g.abs().sum()) == 0.0 for g in grads)


def test_group_norm_silu_gradcheck_float64():
    x, w, b, r = (t.double().requires_grad_() for t in inputs((2, 4, 3, 5)))
    assert torch.autograd.gradcheck(lambda *a: group_norm_silu(a[0], a[1], a[2], 2, 1e-3, a[3]), (x, w, b, r))
    assert torch.autograd.gradcheck(lambda *a: group_norm_silu(*a, 4, 1e-3), (x[:, :, :1, :2], w, b))


def test_opcheck_group_norm_silu(device):
    x, w, b, r = inputs((2, 6, 4, 3), device)
    strided = r.transpose(2, 3).contiguous().transpose(2, 3)  # the fake kernels' strides as the kernels'
    for residual in (r, None, strided):
        args = (x.requires_grad_(), w.requires_grad_(), b.requires_grad_(), 3, 1e-5, residual)
        torch.library.opcheck(torch.ops.t3fast.group_norm_silu.default, args)
        _, mean, rstd = torch.ops.t3fast.group_norm_silu(*args)
        grad = rand(2, 6, 4, 3, device=device, seed=6)
        torch.library.opcheck(torch.ops.t3fast.group_norm_silu_backward.default,
                              (grad, x.detach(), w.detach(), b.detach(), residual, mean.detach(), rstd.detach(), 3))


def test_the_statistics_are_the_groups(device):
    x, w, b, _ = inputs((2, 6, 7), device, residual=False)
    _, mean, rstd = torch.ops.t3fast.group_norm_silu(x, w, b, 3, 1e-5)
    groups = x.view(2, 3, -1)
    torch.testing.assert_close(mean, groups.mean(-1))
    torch.testing.assert_close(rstd, (groups.var(-1, unbiased=False) + 1e-5).rsqrt())


def test_under_autocast_it_computes_in_float32():
    """As group_norm under CUDA's autocast (the CPU's keeps group_norm in bfloat16; the CPU kernel
    has no lower precision): a bfloat16 activation meets float32 parameters in float32."""
    x, w, b, r = inputs((2, 4, 5, 6))
    low = x.bfloat16()  # what an autocast convolution hands it
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = group_norm_silu(low, w, b, 2, 1e-5, r)
    assert got.dtype == torch.float32
    torch.testing.assert_close(got, reference.group_norm_silu(low.float(), w, b, 2, 1e-5, r))


def test_double_backward_is_refused_naming_the_reference():
    x, w, b, _ = (t.double().requires_grad_() if t is not None else None for t in inputs((1, 2, 4), residual=False))
    (grad,) = torch.autograd.grad(group_norm_silu(x, w, b, 1).pow(2).sum(), x, create_graph=True)
    with pytest.raises(RuntimeError, match="reference.group_norm_silu"):
        grad.sum().backward()


def test_the_encoder_backends_agree():
    """The encoder's norms fused or as the modules: the same volume to float32's rounding."""
    from t3fast.models.config import AutoencoderConfig
    from t3fast.models.encoder import TriplaneEncoder

    torch.manual_seed(0)
    cfg = AutoencoderConfig(grid=(20, 16, 8), embed_dim=4, full_res_channels=8, full_res_blocks=1,
                            half_res_channels=16, half_res_blocks=1, channels=8)
    fused, ref = TriplaneEncoder(cfg), TriplaneEncoder(cfg, backend="reference")
    ref.load_state_dict(fused.state_dict())
    labels = torch.randint(0, cfg.num_classes, (2, *cfg.grid))
    torch.testing.assert_close(fused.volume(labels), ref.volume(labels), rtol=1e-5, atol=1e-5)


_X, _W, _B = torch.zeros(2, 4, 3), torch.ones(4), torch.zeros(4)


@pytest.mark.parametrize("args, message", [
    ((torch.zeros(4), _W, _B, 2), r"input must have at least 2 dims \[B, C, \*\], got 1 dims"),
    ((_X.int(), _W.int(), _B.int(), 2), "input must be float32 or float64 on CPU, got Int"),
    ((_X, torch.ones(3), _B, 2), r"weight.shape\[0\] \(C, as input.shape\[1\]\) must be 4, got 3"),
    ((_X, _W, torch.zeros(4, 1), 2), r"bias must have 1 dims \[C\], got 2 dims"),
    ((_X, _W.double(), _B, 2), "weight must have the dtype of input"),
    ((_X, _W, _B, 3), "groups must be a positive divisor of the 4 channels, got 3"),
    ((_X, _W, _B, 0), "groups must be a positive divisor of the 4 channels, got 0"),
    ((_X, _W, _B, 2, -1.0), "eps must be finite and >= 0, got -1"),
    ((_X, _W, _B, 2, 1e-5, torch.zeros(2, 4, 2)), r"residual must have the shape of input \[2, 4, 3\]"),
    ((_X, _W, _B, 2, 1e-5, torch.zeros(2, 4, 3, dtype=torch.float64)), "residual must have the dtype of input"),
])
def test_bad_input_names_the_problem(args, message):
    with pytest.raises(RuntimeError, match=f"t3fast.group_norm_silu: {message}"):
        group_norm_silu(*args)


def test_parameters_on_another_device_are_refused_naming_them():
    with pytest.raises(RuntimeError, match=r"t3fast.group_norm_silu: weight must be on the same device as input "
                                           r"\(cpu\), got meta"):
        group_norm_silu(_X, _W.to("meta"), _B, 2)


def test_backward_with_wrong_statistics_names_them():
    stats = torch.zeros(2, 3)
    with pytest.raises(RuntimeError, match=r"group_norm_silu_backward: mean must have shape \[2, 2\] "
                                           r"\(batch, groups\), got \[2, 3\]"):
        torch.ops.t3fast.group_norm_silu_backward(_X, _X, _W, _B, None, stats, stats, 2)
