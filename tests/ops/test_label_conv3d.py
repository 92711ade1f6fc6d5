"""label_conv3d: parity with the one-hot convolution reference and with the embedding and
convolution it replaces, forward and backward; opcheck, gradcheck, torch.compile."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from t3fast.ops import label_conv3d, reference


def make(shape, classes, channels, device="cpu", dtype=torch.float32, label_dtype=torch.uint8, seed=0):
    g = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, classes, shape, generator=g).to(device=device, dtype=label_dtype)
    table = torch.randn(27, classes, channels, generator=g, dtype=dtype).to(device)
    return labels, table


@pytest.mark.parametrize("label_dtype", [torch.uint8, torch.int32, torch.int64])
@pytest.mark.parametrize("shape, classes, channels", [
    ((0, 4, 5, 3), 4, 8),          # empty batch
    ((1, 1, 1, 1), 1, 1),          # one voxel: only the centre tap is inside
    ((2, 7, 5, 3), 5, 3),          # odd sizes, a channel count without a compiled special case
    ((1, 9, 11, 16), 18, 8),       # Occ3D's classes and height, the shipped stem width
    ((2, 6, 4, 5), 18, 32),        # the papers' stem width
])
def test_matches_reference(device, shape, classes, channels, label_dtype):
    labels, table = make(shape, classes, channels, device, label_dtype=label_dtype)
    table.requires_grad_()
    got = label_conv3d(labels, table)
    want = reference.label_conv3d(labels, table)
    assert got.shape == (shape[0], channels, *shape[1:])
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    upstream = torch.randn(want.shape, generator=torch.Generator().manual_seed(1)).to(device)
    (g_got,) = torch.autograd.grad(got, table, upstream)
    (g_want,) = torch.autograd.grad(want, table, upstream)
    torch.testing.assert_close(g_got, g_want, rtol=1e-5, atol=1e-5)


def test_equals_the_embedding_and_convolution_it_replaces(device):
    """conv3d(embedding(labels), weight, padding=1) through its table."""
    g = torch.Generator().manual_seed(2)
    labels = torch.randint(0, 18, (2, 10, 9, 16), generator=g).to(device)
    embed = torch.randn(18, 8, generator=g).to(device)
    weight = torch.randn(16, 8, 3, 3, 3, generator=g).to(device)
    want = F.conv3d(F.embedding(labels, embed).permute(0, 4, 1, 2, 3), weight, padding=1)
    table = torch.einsum("ceijk,qe->ijkqc", weight, embed).reshape(27, 18, 16)
    torch.testing.assert_close(label_conv3d(labels, table), want, rtol=1e-4, atol=1e-4)


def test_taps_run_in_the_documented_order():
    """One voxel of class 1 in a 3 x 3 x 3 volume: the output at its neighbour v - t reads tap t."""
    labels = torch.zeros(1, 3, 3, 3, dtype=torch.uint8)
    labels[0, 1, 1, 1] = 1
    table = torch.zeros(27, 2, 1)
    table[:, 1, 0] = torch.arange(1.0, 28.0)
    out = label_conv3d(labels, table)[0, 0]
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                tap = 9 * (dx + 1) + 3 * (dy + 1) + dz + 1
                assert out[1 - dx, 1 - dy, 1 - dz] == tap + 1


def test_non_contiguous_labels_and_table(device):
    labels, table = make((2, 6, 5, 4), 7, 8, device)
    labels_nc = labels.transpose(1, 3).contiguous().transpose(1, 3)
    table_nc = table.transpose(0, 2).contiguous().transpose(0, 2)
    assert not labels_nc.is_contiguous() and not table_nc.is_contiguous()
    torch.testing.assert_close(label_conv3d(labels_nc, table_nc), reference.label_conv3d(labels, table),
                               rtol=1e-5, atol=1e-5)


def test_gradcheck_float64():
    labels, table = make((2, 3, 4, 3), 4, 2, dtype=torch.float64)
    table.requires_grad_()
    assert torch.autograd.gradcheck(lambda t: label_conv3d(labels, t), (table,))
    assert torch.autograd.gradgradcheck(lambda t: label_conv3d(labels, t), (table,))


def test_opcheck(device):
    labels, table = make((2, 4, 3, 5), 6, 4, device)
    torch.library.opcheck(torch.ops.t3fast.label_conv3d.default, (labels, table.requires_grad_()))
    grad = torch.randn(2, 4, 4, 3, 5, device=device, requires_grad=True)
    torch.library.opcheck(torch.ops.t3fast.label_conv3d_backward.default, (grad, labels, 6))


def test_backward_is_deterministic_and_independent_of_threads():
    """Private per-thread tables added in thread order: the same bits on every call."""
    labels, table = make((2, 33, 17, 16), 18, 8)
    grad = torch.randn(2, 8, 33, 17, 16)
    first = torch.ops.t3fast.label_conv3d_backward.default(grad, labels, 18)
    assert torch.equal(first, torch.ops.t3fast.label_conv3d_backward.default(grad, labels, 18))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        single = torch.ops.t3fast.label_conv3d_backward.default(grad, labels, 18)
    finally:
        torch.set_num_threads(threads)
    torch.testing.assert_close(first, single, rtol=1e-5, atol=1e-4)


def test_backward_rejects_labels_outside_the_table():
    labels = torch.full((1, 3, 3, 3), 4, dtype=torch.uint8)
    message = r"t3fast\.label_conv3d_backward: labels must be class ids in \[0, 4\), got 4"
    with pytest.raises(RuntimeError, match=message):
        torch.ops.t3fast.label_conv3d_backward.default(torch.randn(1, 2, 3, 3, 3), labels, 4)
    with pytest.raises(RuntimeError, match=r"grad\.shape\[4\] \(Z, as labels\) must be 3, got 2"):
        torch.ops.t3fast.label_conv3d_backward.default(torch.randn(1, 2, 3, 3, 2), labels, 5)


def test_torch_compile_fullgraph(device):
    labels, table = make((1, 5, 4, 6), 5, 8, device)
    compiled = torch.compile(label_conv3d, fullgraph=True, backend="aot_eager")
    torch.testing.assert_close(compiled(labels, table), label_conv3d(labels, table))


def test_float32_from_bfloat16_under_cpu_autocast():
    labels, table = make((1, 4, 4, 4), 3, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = label_conv3d(labels, table.bfloat16())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, label_conv3d(labels, table.bfloat16().float()))
