"""Inputs of the benchmarked workloads, shared by the timed and the memory benchmarks, and
the work each one does (FLOPs, compulsory bytes) for roofline fractions.

Two environment variables select where and how big:

* ``T3FAST_BENCH_DEVICE``: ``cpu`` (default) or ``cuda``; inputs are created on that device
  and every timed call ends with ``torch.cuda.synchronize()`` there.
* ``T3FAST_BENCH_QUICK=1``: tiny sizes and two rounds, to check the benchmarks themselves run.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
from collections.abc import Iterator

import torch

import t3fast.ops as fused
from t3fast.ops import reference

DEVICE = os.environ.get("T3FAST_BENCH_DEVICE", "cpu")
QUICK = os.environ.get("T3FAST_BENCH_QUICK", "0") == "1"

GRID = (20, 20, 8) if QUICK else (200, 200, 16)  # Occ3D-nuScenes voxels
PLANES = (10, 10, 8) if QUICK else (100, 100, 16)  # triplane resolution of the paper
POINTS = 2_000 if QUICK else 200_000  # sampled query points of a training step
CHANNELS = 8 if QUICK else 64  # axis_pool / delta_fuse channels
# channels C_f, hidden width, hidden layers
DECODERS = {"small": (16, 64, 2), "paper": (64, 256, 4)}
IMPLS = {"fused": fused, "reference": reference}
FLOAT_BYTES = 4  # every workload runs in float32


@contextlib.contextmanager
def reference_ops(model: torch.nn.Module) -> Iterator[None]:
    """A world model's forecast with every fused op it calls run as its pure-PyTorch reference:
    the encoder's stem and norms, the decoder, the forecasters' delta fusion and the flow forecaster's
    matching costs."""
    import t3fast.models.flow_forecaster as flow_module
    import t3fast.models.forecaster as forecaster_module

    swapped = [(forecaster_module, "delta_fuse"), (flow_module, "delta_fuse"), (flow_module, "matching_costs")]
    fused_ops = [getattr(module, name) for module, name in swapped]
    backends = model.decoder.backend, model.encoder.backend
    for module, name in swapped:
        setattr(module, name, getattr(reference, name))
    model.decoder.backend = model.encoder.backend = "reference"
    try:
        yield
    finally:
        for (module, name), op in zip(swapped, fused_ops):
            setattr(module, name, op)
        model.decoder.backend, model.encoder.backend = backends


def rounds(n: int) -> int:
    """Timed rounds of a benchmark written for ``n`` CPU rounds: 2 when quick, at least 10 on a
    GPU (calls take milliseconds there)."""
    if QUICK:
        return 2
    return max(n, 10) if DEVICE == "cuda" else n


def synchronized(fn):
    """``fn`` followed by a device synchronisation, so the timer sees the kernels finish."""
    if DEVICE != "cuda":
        return fn

    @functools.wraps(fn)
    def call(*args, **kwargs):
        out = fn(*args, **kwargs)
        torch.cuda.synchronize()
        return out

    return call


def make_decode_inputs(decoder: str, batch: int = 1, classes: int = 18, pe_freqs: int = 6,
                       requires_grad: bool = False, seed: int = 0, device: str | None = None):
    """Planes, weights and biases of a decoder config (see DECODERS), on ``device``
    (default ``DEVICE``)."""
    device = device or DEVICE
    channels, hidden, layers = DECODERS[decoder]
    g = torch.Generator().manual_seed(seed)
    px, py, pz = PLANES
    planes = [torch.randn(batch, channels, *s, generator=g) for s in ((px, py), (px, pz), (py, pz))]
    widths = [channels + 6 * pe_freqs, *[hidden] * layers, classes]
    weights = [torch.randn(o, i, generator=g) / i**0.5 for i, o in zip(widths[:-1], widths[1:])]
    biases = [torch.zeros(o) for o in widths[1:]]
    planes, weights, biases = ([t.to(device) for t in group] for group in (planes, weights, biases))
    for t in (*planes, *weights, *biases):
        t.requires_grad_(requires_grad)
    return planes, weights, biases, pe_freqs


@functools.lru_cache(maxsize=4)
def query_points(batch: int, n: int, device: str) -> torch.Tensor:
    """``[batch, n, 3]`` points in [-1, 1], made once (outside the timed calls)."""
    points = torch.rand(batch, n, 3, generator=torch.Generator().manual_seed(1))
    return (points * 2 - 1).to(device)


def run_decode(impl: str, args, query: str):
    """query: "grid" (full grid logits), "argmax" (full grid labels) or "points:N"."""
    planes, weights, biases, pe_freqs = args
    op = IMPLS[impl].triplane_decode
    if query == "grid":
        return op(*planes, weights, biases, grid=GRID, pe_freqs=pe_freqs)
    if query == "argmax":
        return op(*planes, weights, biases, grid=GRID, pe_freqs=pe_freqs, argmax=True)
    n = int(query.split(":")[1])
    points = query_points(planes[0].shape[0], n, str(planes[0].device))
    return op(*planes, weights, biases, points=points, pe_freqs=pe_freqs)


# ---- work per call: model FLOPs and compulsory bytes (inputs read once, outputs written once)


def decode_cost(decoder: str, query: str, backward: bool = False, batch: int = 1, classes: int = 18,
                pe_freqs: int = 6) -> dict[str, float]:
    """FLOPs and bytes of one :func:`run_decode` call (``backward``: plus the gradients of
    planes, weights and biases).

    Per point: the MLP's ``2 * sum(in * out)`` plus 24 C for the three bilinear lookups (4 taps,
    multiply-add); the backward pass doubles the MLP (input and weight gradients) and repeats
    the lookups as a scatter. Bytes: planes, weights and points read, logits (4 bytes per class)
    or labels (1 byte) written; the backward pass adds the upstream gradient read and the
    plane and weight gradients written.
    """
    channels, hidden, layers = DECODERS[decoder]
    widths = [channels + 6 * pe_freqs, *[hidden] * layers, classes]
    mlp = 2 * sum(i * o for i, o in zip(widths[:-1], widths[1:]))
    params = sum(i * o + o for i, o in zip(widths[:-1], widths[1:]))
    px, py, pz = PLANES
    plane_values = batch * channels * (px * py + px * pz + py * pz)
    if query in ("grid", "argmax"):
        n, point_bytes = batch * GRID[0] * GRID[1] * GRID[2], 0
    else:
        n = batch * int(query.split(":")[1])
        point_bytes = n * 3 * FLOAT_BYTES
    out_bytes = n if query == "argmax" else n * classes * FLOAT_BYTES
    flops = n * (mlp + 24 * channels)
    nbytes = (plane_values + params) * FLOAT_BYTES + point_bytes + out_bytes
    if backward:
        flops += n * (2 * mlp + 24 * channels)
        nbytes += n * classes * FLOAT_BYTES + (plane_values + params) * FLOAT_BYTES
    return {"flops": float(flops), "bytes": float(nbytes)}


def axis_pool_shape() -> tuple[int, ...]:
    """``[B, C, X, Y, Z]`` of the axis_pool benchmarks."""
    px, py, pz = PLANES
    return (2, CHANNELS, px, py, pz)


def axis_pool_cost(backward: bool = False) -> dict[str, float]:
    """Forward: each voxel added into three sums; bytes: the volume read, three planes written.
    Backward: three scaled plane values summed per voxel (5 FLOPs); planes read, volume written."""
    b, c, x, y, z = axis_pool_shape()
    volume, planes = b * c * x * y * z, b * c * (x * y + x * z + y * z)
    flops, values = 3 * volume, volume + planes
    if backward:
        flops, values = flops + 5 * volume, values + planes + volume
    return {"flops": float(flops), "bytes": float(values * FLOAT_BYTES)}


def delta_fuse_shapes() -> list[tuple[int, int, int, int]]:
    """``[B, C, H, W]`` of the three planes of one triplane."""
    px, py, pz = PLANES
    return [(1, CHANNELS, px, py), (1, CHANNELS, px, pz), (1, CHANNELS, py, pz)]


def delta_fuse_cost(backward: bool = False) -> dict[str, float]:
    """All three planes. Forward: the 1x1 convolution (2 C C_in per pixel) plus the delta and
    bias additions; delta, prev read, the result written. Backward: input and weight gradients
    (4 C C_in per pixel) and the bias sum; the upstream gradient and prev read, both input
    gradients written."""
    flops = values = 0
    for b, c, h, w in delta_fuse_shapes():
        pixels = b * h * w
        flops += pixels * (2 * c * c + 2 * c)
        values += 3 * pixels * c + c * c + c
        if backward:
            flops += pixels * (4 * c * c + c)
            values += 4 * pixels * c + c * c + c
    return {"flops": float(flops), "bytes": float(values * FLOAT_BYTES)}


#: the flow forecaster's matching costs at batch 1: the pairs (present, previous) and (previous,
#: the one before) of the shipped model's xy planes, radius 6 (169 shifts)
MATCHING_SHAPE, MATCHING_RADIUS = (2, 8, 100, 100), 6


def matching_costs_cost(backward: bool = False) -> dict[str, float]:
    """Forward: per output (B * 169 shifts * H * W) a subtraction, an absolute value and an
    addition per channel; compulsory bytes: both planes read, the costs written. Backward: a
    sign and a multiply-add per shift, channel and cell for each plane; the upstream gradient
    and both planes read, both gradients written."""
    b, c, h, w = MATCHING_SHAPE
    outputs = b * (2 * MATCHING_RADIUS + 1) ** 2 * h * w
    flops, values = 3 * outputs * c, 2 * b * c * h * w + outputs
    if backward:
        flops, values = flops + 2 * 3 * outputs * c, values + outputs + 4 * b * c * h * w
    return {"flops": float(flops), "bytes": float(values * FLOAT_BYTES)}


#: the encoder's activations of the six frames of a window: the stem's at full resolution, and
#: the residual block's at half resolution (with the block's input added)
NORM_SHAPES = {"stem": (6, 8, *GRID), "block": (6, 16, GRID[0] // 2, GRID[1] // 2, GRID[2])}


def group_norm_silu_cost(shape: tuple[int, ...], residual: bool, backward: bool = False) -> dict[str, float]:
    """Forward: per value a subtraction and two multiply-adds for the statistics, a multiply-add,
    an exponential (counted as one), an addition and a division for the output (one more
    addition with a residual); compulsory bytes: the input (and residual) read, the output
    written. Backward: the silu gradient and the sums (about 12 operations a value), then the
    input's gradient (about 5); the upstream gradient and the input (and residual) read, the
    input's (and residual's) gradient written."""
    values = math.prod(shape)
    flops = values * (9 + residual)
    tensors = 2 + residual
    if backward:
        flops += values * 17
        tensors += 3 + 2 * residual
    return {"flops": float(flops), "bytes": float(tensors * values * FLOAT_BYTES)}


def label_conv3d_cost(channels: int, backward: bool = False) -> dict[str, float]:
    """One 200 x 200 x 16 frame, 18 classes. Forward: 27 table rows of ``channels`` values added
    per voxel; bytes: the uint8 labels read, the output written (the table stays in cache).
    Backward: the output gradient added into 27 rows per voxel; the gradient read as well."""
    voxels = 200 * 200 * 16
    flops = 27 * channels * voxels
    nbytes = voxels + voxels * channels * FLOAT_BYTES + 27 * 18 * channels * FLOAT_BYTES
    if backward:
        flops, nbytes = 2 * flops, nbytes + voxels * channels * FLOAT_BYTES
    return {"flops": float(flops), "bytes": float(nbytes)}
