"""Bad arguments raise errors that name the op, the argument, and expected vs actual."""

from __future__ import annotations

import re

import pytest
import torch

from t3fast.ops import axis_pool, bev_components, delta_fuse, draw_boxes, label_conv3d, triplane_decode

from .test_triplane_decode import make_inputs


def decode_args(**overrides):
    planes, weights, biases = make_inputs(2, 4, (5, 6, 3), [8], 1, 5)
    args = dict(xy=planes[0], xz=planes[1], yz=planes[2], weights=weights, biases=biases,
                grid=(4, 4, 2), pe_freqs=1)
    args.update(overrides)
    return args


def call_decode(args):
    args = dict(args)
    return triplane_decode(args.pop("xy"), args.pop("xz"), args.pop("yz"), args.pop("weights"),
                           args.pop("biases"), **args)


@pytest.mark.parametrize(
    "overrides, pattern",
    [
        (dict(xy=torch.randn(2, 4, 5)), r"xy must have 4 dims \[B, C, X', Y'\], got 3 dims"),
        (dict(xz=torch.randn(2, 3, 5, 3)), r"xz\.shape\[1\] \(channels, as xy\) must be 4, got 3"),
        (dict(yz=torch.randn(2, 4, 7, 3)), r"yz\.shape\[2\] \(Y', as xy\.shape\[3\]\) must be 6"),
        (dict(yz=torch.randn(3, 4, 6, 3)), r"yz\.shape\[0\] \(batch, as xy\) must be 2, got 3"),
        (dict(xy=torch.randn(2, 4, 5, 6, dtype=torch.float64)),
         r"xz must have the dtype of xy \(Double\), got Float"),
        (dict(xy=torch.randint(0, 3, (2, 4, 5, 6))), r"xy must be float32 or float64 on CPU"),
        (dict(weights=[torch.randn(8, 11), torch.randn(5, 8)]),
         r"weights\[0\]\.shape\[1\] \(in features\) must be 10 \(C \+ 6 \* pe_freqs\), got 11"),
        (dict(weights=[torch.randn(8, 10), torch.randn(5, 7)]),
         r"weights\[1\]\.shape\[1\] \(in features\) must be 8 \(the previous layer's out"),
        (dict(biases=[torch.randn(8)]), r"same number of layers, got 2 weights and 1 biases"),
        (dict(biases=[torch.randn(8), torch.randn(4)]), r"biases\[1\]\.shape\[0\] must be 5"),
        (dict(weights=[], biases=[]), r"weights must hold at least one layer"),
        (dict(points=torch.rand(2, 10, 3)), r"exactly one of grid and points .*, got both"),
        (dict(grid=None), r"exactly one of grid and points must be given, got neither"),
        (dict(grid=None, points=torch.rand(2, 10, 2)),
         r"points\.shape\[2\] \(coordinates \(x, y, z\)\) must be 3, got 2"),
        (dict(grid=(4, 4)), r"grid must be \(X, Y, Z\), got 2 values"),
        (dict(grid=(4, -1, 2)), r"grid sizes must be >= 0"),
        (dict(pe_freqs=-1, weights=[torch.randn(8, 4), torch.randn(5, 8)]),
         r"pe_freqs must be in \[0, 30\], got -1"),
    ],
)
def test_triplane_decode_rejects(overrides, pattern):
    with pytest.raises(RuntimeError, match=r"t3fast\.triplane_decode: .*" + pattern):
        call_decode(decode_args(**overrides))


@pytest.mark.parametrize("classes", [0, 300])
def test_triplane_decode_argmax_needs_1_to_256_classes(device, classes):
    planes, weights, biases = make_inputs(2, 4, (5, 6, 3), [8], 1, classes, device=device)
    with pytest.raises(RuntimeError, match=rf"argmax=True needs 1 to 256 classes .* got {classes}"):
        triplane_decode(*planes, weights, biases, grid=(4, 4, 2), pe_freqs=1, argmax=True)


@pytest.mark.parametrize(
    "overrides, pattern",
    [
        (dict(argmax=True), r"live counts the points to decode: it needs points and argmax=True"),
        (dict(grid=None, points=torch.rand(2, 10, 3)), r"it needs points and argmax=True"),
        (dict(grid=None, points=torch.rand(2, 10, 3), argmax=True, live=torch.tensor([1, 2], dtype=torch.int32)),
         r"live must be int64, got Int"),
        (dict(grid=None, points=torch.rand(2, 10, 3), argmax=True, live=torch.tensor([1, 2, 3])),
         r"live must be \[B\] = \[2\] \(one count per batch element\), got \[3\]"),
        (dict(grid=None, points=torch.rand(2, 10, 3), argmax=True, live=torch.tensor([1, 2], device="meta")),
         r"live must be on the same device as xy"),
    ],
)
def test_triplane_decode_rejects_live_counts_it_cannot_use(overrides, pattern):
    args = decode_args(live=torch.tensor([1, 2]))
    args.update(overrides)
    with pytest.raises(RuntimeError, match=r"t3fast\.triplane_decode: .*" + pattern):
        call_decode(args)


def test_mixed_devices_name_the_argument():
    args = decode_args(xz=torch.randn(2, 4, 5, 3, device="meta"))
    pattern = r"xz must be on the same device as xy \(cpu\), got meta"
    with pytest.raises(RuntimeError, match=pattern):
        call_decode(args)
    with pytest.raises(RuntimeError, match=r"prev must be on the same device as delta"):
        delta_fuse(torch.randn(1, 2, 3, 3), torch.randn(1, 2, 3, 3, device="meta"),
                   torch.randn(2, 2))


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_cpu_and_cuda_mixed():
    args = decode_args(xz=torch.randn(2, 4, 5, 3, device="cuda"))
    with pytest.raises(RuntimeError, match=r"xz must be on the same device as xy"):
        call_decode(args)


def test_backward_op_checks_grad_shape():
    planes, weights, biases = make_inputs(2, 4, (5, 6, 3), [8], 1, 5)
    grad = torch.randn(2, 4, 4, 2, 6)
    with pytest.raises(RuntimeError, match=re.escape("grad_out must have shape [2, 4, 4, 2, 5]")):
        torch.ops.t3fast.triplane_decode_backward(grad, *planes, weights, biases, None,
                                                  [4, 4, 2], 1)


@pytest.mark.parametrize(
    "volume, pattern",
    [
        (torch.randn(2, 3, 4, 5), r"volume must have 5 dims \[B, C, X, Y, Z\], got 4 dims"),
        (torch.randn(2, 3, 4, 0, 5), r"volume must have non-empty X, Y, Z"),
        (torch.ones(1, 1, 2, 2, 2, dtype=torch.int32), r"volume must be float32 or float64"),
    ],
)
def test_axis_pool_rejects(volume, pattern):
    with pytest.raises(RuntimeError, match=r"t3fast\.axis_pool: .*" + pattern):
        axis_pool(volume)


@pytest.mark.parametrize(
    "args, pattern",
    [
        ((torch.randn(2, 4, 5), torch.randn(2, 3, 5, 6), torch.randn(4, 3)),
         r"delta must have 4 dims \[B, C, H, W\], got 3 dims"),
        ((torch.randn(2, 4, 5, 6), torch.randn(2, 3, 5, 6), torch.randn(4, 2)),
         r"weight\.shape\[1\] \(C_in, as prev\.shape\[1\]\) must be 3, got 2"),
        ((torch.randn(2, 4, 5, 6), torch.randn(2, 3, 5, 6), torch.randn(5, 3)),
         r"weight\.shape\[0\] \(C, as delta\.shape\[1\]\) must be 4, got 5"),
        ((torch.randn(2, 4, 5, 6), torch.randn(2, 3, 5, 7), torch.randn(4, 3)),
         r"prev\.shape\[3\] \(W, as delta\) must be 6, got 7"),
        ((torch.randn(2, 4, 5, 6), torch.randn(2, 3, 5, 6, dtype=torch.float64),
          torch.randn(4, 3)), r"weight must have the dtype of prev \(Double\), got Float"),
        ((torch.randn(2, 4, 5, 6), torch.randn(2, 3, 5, 6), torch.randn(4, 3), torch.randn(3)),
         r"bias\.shape\[0\] \(C, as delta\.shape\[1\]\) must be 4, got 3"),
    ],
)
def test_delta_fuse_rejects(args, pattern):
    with pytest.raises(RuntimeError, match=r"t3fast\.delta_fuse: .*" + pattern):
        delta_fuse(*args)


@pytest.mark.parametrize(
    "labels, table, pattern",
    [
        (torch.zeros(2, 3, 4, dtype=torch.uint8), torch.randn(27, 5, 4),
         r"labels must have 4 dims \[B, X, Y, Z\], got 3 dims"),
        (torch.zeros(1, 3, 4, 2, dtype=torch.uint8), torch.randn(27, 5),
         r"table must have 3 dims \[27, K, C\], got 2 dims"),
        (torch.zeros(1, 3, 4, 2), torch.randn(27, 5, 4), r"labels must be uint8, int32 or int64 class ids, got Float"),
        (torch.zeros(1, 3, 4, 2, dtype=torch.int16), torch.randn(27, 5, 4),
         r"labels must be uint8, int32 or int64 class ids, got Short"),
        (torch.zeros(1, 3, 4, 2, dtype=torch.uint8), torch.randn(26, 5, 4),
         r"table\.shape\[0\] \(the 3 x 3 x 3 taps\) must be 27, got 26"),
        (torch.zeros(1, 3, 4, 2, dtype=torch.uint8), torch.randn(27, 0, 4), r"table must hold at least one class"),
        (torch.zeros(1, 3, 4, 2, dtype=torch.uint8), torch.randn(27, 5, 4).half(),
         r"table must be float32 or float64 on CPU, got Half"),
        (torch.full((1, 3, 4, 2), 5, dtype=torch.uint8), torch.randn(27, 5, 4),
         r"labels must be class ids in \[0, 5\) \(the rows of table\), got 5"),
        (torch.full((1, 3, 4, 2), -2, dtype=torch.int64), torch.randn(27, 5, 4),
         r"labels must be class ids in \[0, 5\) \(the rows of table\), got -2"),
    ],
)
def test_label_conv3d_rejects(labels, table, pattern):
    with pytest.raises(RuntimeError, match=r"t3fast\.label_conv3d: .*" + pattern):
        label_conv3d(labels, table)


@pytest.mark.parametrize(
    "mask, pattern",
    [
        (torch.zeros(3, 4, dtype=torch.bool), r"mask must have 3 dims \[B, X, Y\], got 2 dims"),
        (torch.zeros(1, 3, 4, 2, dtype=torch.bool), r"mask must have 3 dims \[B, X, Y\], got 4 dims"),
        (torch.zeros(1, 3, 4, dtype=torch.uint8), r"mask must be bool, got Byte"),
        (torch.zeros(1, 3, 4), r"mask must be bool, got Float"),
    ],
)
def test_bev_components_rejects(mask, pattern):
    with pytest.raises(RuntimeError, match=r"t3fast\.bev_components: .*" + pattern):
        bev_components(mask)


def _draw_args(**change):
    args = dict(volume=torch.zeros(2, 5, 6, 3, dtype=torch.uint8), boxes=torch.zeros(2, 4, 6, dtype=torch.float64),
                levels=torch.zeros(4, 2, dtype=torch.long), labels=torch.zeros(4, dtype=torch.uint8),
                lower=(-1.0, -1.0), voxel_size=0.4, reach=2)
    args.update(change)
    return args


@pytest.mark.parametrize(
    "change, pattern",
    [
        (dict(volume=torch.zeros(5, 6, 3, dtype=torch.uint8)), r"volume must have 4 dims \[B, X, Y, Z\], got 3 dims"),
        (dict(volume=torch.zeros(2, 5, 6, 3, dtype=torch.int64)), r"volume must be uint8 labels, got Long"),
        (dict(boxes=torch.zeros(2, 4, 6)), r"boxes must be float64, got Float"),
        (dict(boxes=torch.zeros(3, 4, 6, dtype=torch.float64)), r"boxes\.shape\[0\] \(batch, as volume\) must be 2"),
        (dict(boxes=torch.zeros(2, 4, 5, dtype=torch.float64)), r"boxes\.shape\[2\] \(x, y, cos, sin, half length"),
        (dict(levels=torch.zeros(3, 2, dtype=torch.long)), r"levels\.shape\[0\] \(boxes, as boxes\.shape\[1\]\)"),
        (dict(levels=torch.zeros(4, 2, dtype=torch.int32)), r"levels must be int64, got Int"),
        (dict(labels=torch.zeros(4, dtype=torch.int64)), r"labels must be uint8, got Long"),
        (dict(labels=torch.zeros(5, dtype=torch.uint8)), r"labels\.shape\[0\] \(boxes, as boxes\.shape\[1\]\)"),
        (dict(levels=torch.zeros(1, 2, 4, 2, dtype=torch.long)),
         r"levels must have 2 dims \[M, 2\] \(every volume's\) or 3 dims \[B, M, 2\] \(each volume's\), got 4"),
        (dict(levels=torch.zeros(3, 4, 2, dtype=torch.long), labels=torch.zeros(3, 4, dtype=torch.uint8)),
         r"levels\.shape\[0\] \(batch, as volume\) must be 2, got 3"),
        (dict(levels=torch.zeros(2, 4, 2, dtype=torch.long)),
         r"labels must have 2 dims \[B, M\], as levels is each volume's, got 1 dims"),
        (dict(labels=torch.zeros(2, 4, dtype=torch.uint8)),
         r"labels must have 1 dim \[M\], as levels is every volume's, got 2 dims"),
        (dict(lower=(0.0,)), r"lower must hold the grid's lower x and y, got 1 values"),
        (dict(voxel_size=0.0), r"voxel_size must be positive, got 0"),
        (dict(reach=-1), r"reach must be at least 0, got -1"),
    ],
)
def test_draw_boxes_rejects(change, pattern):
    with pytest.raises(RuntimeError, match=r"t3fast\.draw_boxes: .*" + pattern):
        draw_boxes(**_draw_args(**change))
