"""Fused operators versus their PyTorch references. Run with
``pytest benchmarks --benchmark-only``; each group is read as a reference/fused ratio.

CPU by default; ``T3FAST_BENCH_DEVICE=cuda`` runs the same workloads on the GPU (see
``workloads``). Each benchmark's ``extra_info`` holds the FLOPs and compulsory bytes of one call."""

from __future__ import annotations

import contextlib

import pytest
import torch
from _peak_memory import peak_memory_mb
from workloads import (
    DEVICE,
    GRID,
    IMPLS,
    MATCHING_RADIUS,
    MATCHING_SHAPE,
    NORM_SHAPES,
    POINTS,
    axis_pool_cost,
    axis_pool_shape,
    decode_cost,
    delta_fuse_cost,
    delta_fuse_shapes,
    group_norm_silu_cost,
    label_conv3d_cost,
    make_decode_inputs,
    matching_costs_cost,
    query_points,
    rounds,
    run_decode,
    synchronized,
)

IMPL_NAMES = ["fused", "reference"]
# precisions of the decode benchmarks: float32 inputs computed in float32, in TF32
# (allow_tf32 on) or under bfloat16 autocast; the CPU kernels compute in float32 only
PRECISIONS = ["fp32", "tf32", "bf16"] if DEVICE == "cuda" else ["fp32"]


@contextlib.contextmanager
def precision(name: str):
    """The region a benchmark of precision ``name`` runs in: TF32 matmuls allowed for "tf32",
    bfloat16 autocast for "bf16", neither for "fp32"."""
    if name == "bf16":
        with torch.autocast(DEVICE, dtype=torch.bfloat16):
            yield
        return
    previous = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = name == "tf32"
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = previous


def _group(name: str, precision_name: str) -> str:
    """Benchmark group of a decode workload; float32 groups keep their plain names."""
    return name if precision_name == "fp32" else f"{name} {precision_name}"


@pytest.mark.parametrize("impl", IMPL_NAMES)
@pytest.mark.parametrize("precision_name", PRECISIONS)
@pytest.mark.parametrize("decoder", ["small", "paper"])
@pytest.mark.parametrize("query", ["grid", "argmax"])
def test_decode_grid(benchmark, query, decoder, precision_name, impl):
    """Full 200x200x16 grid to logits ("grid") or to uint8 labels ("argmax": the argmax mode
    versus the reference's logits.argmax()), with the peak memory of one float32 call."""
    benchmark.group = _group(f"decode grid {'fwd' if query == 'grid' else 'labels'} {decoder}", precision_name)
    args = make_decode_inputs(decoder)
    benchmark.extra_info.update(decode_cost(decoder, query), precision=precision_name)
    peak = peak_memory_mb(impl, {"decoder": decoder}, query) if precision_name == "fp32" else None
    if peak is not None:
        benchmark.extra_info["peak_mb"] = peak

    def call():
        with torch.no_grad(), precision(precision_name):
            return run_decode(impl, args, query)

    benchmark.pedantic(synchronized(call), rounds=rounds(3), warmup_rounds=1)


@pytest.mark.parametrize("impl", IMPL_NAMES)
@pytest.mark.parametrize("precision_name", PRECISIONS)
@pytest.mark.parametrize("decoder", ["small", "paper"])
def test_decode_points_forward_backward(benchmark, decoder, precision_name, impl):
    """200k sampled points: forward (in the precision's region, as a training step under AMP),
    then backward to planes, weights and biases."""
    benchmark.group = _group(f"decode {POINTS // 1000}k pts fwd+bwd {decoder}", precision_name)
    args = make_decode_inputs(decoder, requires_grad=True)
    planes, weights, biases, _ = args
    params = [*planes, *weights, *biases]
    benchmark.extra_info.update(decode_cost(decoder, f"points:{POINTS}", backward=True), precision=precision_name)

    def step():
        with precision(precision_name):
            out = run_decode(impl, args, f"points:{POINTS}")
        # as a training step: the backward outside autocast (it follows the forward's
        # dtypes), with the TF32 setting of the forward
        with precision("fp32" if precision_name == "bf16" else precision_name):
            return torch.autograd.grad(out, params, torch.ones_like(out))

    benchmark.pedantic(synchronized(step), rounds=rounds(3), warmup_rounds=1)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_decode_live_points(benchmark, impl):
    """What a GPU forecast decodes beyond the present grid: a frame-sized buffer of points (the
    voxels beyond the grid gathered to its front, 15 % of a 200x200x16 frame here) with its
    filled length on the device (``live``), to labels, small decoder: the fused op decodes the
    filled part; the reference decodes the whole buffer and masks the rest."""
    benchmark.group = "decode labels, 15% of a frame's buffer live, small"
    planes, weights, biases, pe_freqs = make_decode_inputs("small")
    n = GRID[0] * GRID[1] * GRID[2]
    points = query_points(1, n, DEVICE)
    live = torch.tensor([n * 15 // 100], device=DEVICE)
    benchmark.extra_info.update(decode_cost("small", f"points:{int(live)}"))
    op = IMPLS[impl].triplane_decode

    def call():
        with torch.no_grad():
            return op(*planes, weights, biases, points=points, pe_freqs=pe_freqs, argmax=True, live=live)

    benchmark.pedantic(synchronized(call), rounds=rounds(3), warmup_rounds=1)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_axis_pool(benchmark, impl):
    benchmark.group = f"axis_pool [{','.join(map(str, axis_pool_shape()))}]"
    volume = torch.randn(*axis_pool_shape(), device=DEVICE)
    benchmark.extra_info.update(axis_pool_cost())
    benchmark.pedantic(synchronized(IMPLS[impl].axis_pool), args=(volume,), rounds=rounds(20), warmup_rounds=2)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_axis_pool_backward(benchmark, impl):
    benchmark.group = f"axis_pool fwd+bwd [{','.join(map(str, axis_pool_shape()))}]"
    volume = torch.randn(*axis_pool_shape(), device=DEVICE, requires_grad=True)
    benchmark.extra_info.update(axis_pool_cost(backward=True))

    def step():
        planes = IMPLS[impl].axis_pool(volume)
        return torch.autograd.grad(planes, volume, [torch.ones_like(p) for p in planes])

    benchmark.pedantic(synchronized(step), rounds=rounds(10), warmup_rounds=2)


def _triplane_planes(requires_grad: bool):
    g = torch.Generator().manual_seed(0)
    shapes = delta_fuse_shapes()
    make = lambda s: torch.randn(*s, generator=g).to(DEVICE).requires_grad_(requires_grad)  # noqa: E731
    channels = shapes[0][1]
    deltas = [make(s) for s in shapes]
    prevs = [make(s) for s in shapes]
    weights = [make((channels, channels)) for _ in shapes]
    biases = [make((channels,)) for _ in shapes]
    return list(zip(deltas, prevs, weights, biases))


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_delta_fuse(benchmark, impl):
    """The three planes of a [1, 64, ...] triplane at 100x100x16."""
    benchmark.group = f"delta_fuse triplane C={delta_fuse_shapes()[0][1]}"
    planes = _triplane_planes(False)
    op = IMPLS[impl].delta_fuse
    benchmark.extra_info.update(delta_fuse_cost())
    benchmark.pedantic(synchronized(lambda: [op(*p) for p in planes]), rounds=rounds(50), warmup_rounds=5)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_delta_fuse_backward(benchmark, impl):
    benchmark.group = f"delta_fuse fwd+bwd triplane C={delta_fuse_shapes()[0][1]}"
    planes = _triplane_planes(True)
    benchmark.extra_info.update(delta_fuse_cost(backward=True))
    op = IMPLS[impl].delta_fuse
    inputs = [t for p in planes for t in p]

    def step():
        outs = [op(*p) for p in planes]
        return torch.autograd.grad(outs, inputs, [torch.ones_like(o) for o in outs])

    benchmark.pedantic(synchronized(step), rounds=rounds(30), warmup_rounds=3)


def _matching_planes(requires_grad: bool):
    g = torch.Generator().manual_seed(0)
    return [torch.randn(*MATCHING_SHAPE, generator=g).tanh().to(DEVICE).requires_grad_(requires_grad)
            for _ in range(2)]


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_matching_costs(benchmark, impl):
    """The flow forecaster's two pairs of xy planes, 169 shifts each."""
    benchmark.group = f"matching_costs {list(MATCHING_SHAPE)} r={MATCHING_RADIUS}"
    present, previous = _matching_planes(False)
    op = IMPLS[impl].matching_costs
    benchmark.extra_info.update(matching_costs_cost())
    benchmark.pedantic(synchronized(lambda: op(present, previous, MATCHING_RADIUS)), rounds=rounds(20),
                       warmup_rounds=3)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_matching_costs_backward(benchmark, impl):
    benchmark.group = f"matching_costs fwd+bwd {list(MATCHING_SHAPE)} r={MATCHING_RADIUS}"
    present, previous = _matching_planes(True)
    op = IMPLS[impl].matching_costs
    benchmark.extra_info.update(matching_costs_cost(backward=True))

    def step():
        out = op(present, previous, MATCHING_RADIUS)
        return torch.autograd.grad(out, (present, previous), torch.ones_like(out))

    benchmark.pedantic(synchronized(step), rounds=rounds(10), warmup_rounds=2)


def _stem_inputs(channels: int, requires_grad: bool = False):
    """One Occ3D frame of labels, and a stem of ``channels`` outputs over an 8-wide embedding
    (the shipped encoder's sizes at 8; the papers' at 32 over 16)."""
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 18, (1, 200, 200, 16), generator=g, dtype=torch.uint8).to(DEVICE)
    embed_dim = 8 if channels == 8 else 16
    embed = torch.randn(18, embed_dim, generator=g).to(DEVICE).requires_grad_(requires_grad)
    weight = torch.randn(channels, embed_dim, 3, 3, 3, generator=g).to(DEVICE).requires_grad_(requires_grad)
    return labels, embed, weight


def _stem(impl: str, labels, embed, weight):
    """The stem convolution of the embedded labels: as one label_conv3d over the table of the
    embedding and the weights (fused), or as the embedding and the conv3d it replaces."""
    if impl == "reference":
        return torch.nn.functional.conv3d(torch.nn.functional.embedding(labels.long(), embed)
                                          .permute(0, 4, 1, 2, 3).contiguous(), weight, padding=1)
    table = torch.einsum("ceijk,qe->ijkqc", weight, embed).reshape(27, 18, weight.shape[0])
    return IMPLS["fused"].label_conv3d(labels, table)


@pytest.mark.parametrize("channels", [8, 32])
@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_label_conv3d(benchmark, impl, channels):
    """The encoder's stem on a 200 x 200 x 16 frame; the reference is the embedding + conv3d."""
    benchmark.group = f"label_conv3d stem [1,200,200,16] C={channels}"
    inputs = _stem_inputs(channels)
    benchmark.extra_info.update(label_conv3d_cost(channels))
    benchmark.pedantic(synchronized(lambda: _stem(impl, *inputs)), rounds=rounds(10), warmup_rounds=2)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_label_conv3d_backward(benchmark, impl):
    benchmark.group = "label_conv3d stem fwd+bwd [1,200,200,16] C=32"
    labels, embed, weight = _stem_inputs(32, requires_grad=True)
    benchmark.extra_info.update(label_conv3d_cost(32, backward=True))

    def step():
        out = _stem(impl, labels, embed, weight)
        return torch.autograd.grad(out, (embed, weight), torch.ones_like(out))

    benchmark.pedantic(synchronized(step), rounds=rounds(3), warmup_rounds=1)


def _norm_inputs(block: str, requires_grad: bool):
    """An activation of the encoder (``block``: "stem" or "block", which adds a residual), its
    GroupNorm's 8 groups' weight and bias."""
    g = torch.Generator().manual_seed(0)
    shape = NORM_SHAPES[block]
    x = torch.randn(*shape, generator=g).to(DEVICE).requires_grad_(requires_grad)
    w, b = (torch.randn(shape[1], generator=g).to(DEVICE).requires_grad_(requires_grad) for _ in range(2))
    r = torch.randn(*shape, generator=g).to(DEVICE).requires_grad_(requires_grad) if block == "block" else None
    return x, w, b, r


@pytest.mark.parametrize("block", list(NORM_SHAPES))
@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_group_norm_silu(benchmark, impl, block):
    """The encoder's GroupNorm + (residual add) + SiLU of a window's six frames; the reference is
    the three ops."""
    x, w, b, r = _norm_inputs(block, False)
    benchmark.group = f"group_norm_silu {block} {list(x.shape)}"
    benchmark.extra_info.update(group_norm_silu_cost(tuple(x.shape), r is not None))
    op = IMPLS[impl].group_norm_silu
    benchmark.pedantic(synchronized(lambda: op(x, w, b, 8, 1e-5, r)), rounds=rounds(10), warmup_rounds=2)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_group_norm_silu_backward(benchmark, impl):
    x, w, b, r = _norm_inputs("block", True)
    benchmark.group = f"group_norm_silu fwd+bwd block {list(x.shape)}"
    benchmark.extra_info.update(group_norm_silu_cost(tuple(x.shape), True, backward=True))
    op = IMPLS[impl].group_norm_silu

    def step():
        out = op(x, w, b, 8, 1e-5, r)
        return torch.autograd.grad(out, (x, w, b, r), torch.ones_like(out))

    benchmark.pedantic(synchronized(step), rounds=rounds(5), warmup_rounds=1)


def _agent_masks() -> torch.Tensor:
    """The agent columns (vehicles and humans) of the six observed frames of a synthetic
    validation window: the masks the tracker finds its agents in ``[6, 200, 200]``."""
    from t3fast.data.classes import AGENT_CLASSES, in_classes
    from t3fast.data.synthetic import SyntheticDriving

    frames = SyntheticDriving("val", 1, 20, stride=9)[0].occ[:6]
    return in_classes(frames, torch.tensor(AGENT_CLASSES)).any(-1).to(DEVICE)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_bev_components(benchmark, impl):
    """The agents' 8-connected components in six frames; the reference is the label propagation
    the tracker ran before (a host synchronisation per round)."""
    benchmark.group = "bev_components agents [6,200,200]"
    masks = _agent_masks()
    # no arithmetic to speak of (comparisons and pointer chasing); bytes: the mask read, int64 labels written
    benchmark.extra_info.update(flops=0.0, bytes=float(masks.numel() * 9))
    benchmark.pedantic(synchronized(lambda: IMPLS[impl].bev_components(masks)), rounds=rounds(20), warmup_rounds=2)


def _forecast_boxes(count: int = 40, steps: int = 6) -> tuple[torch.Tensor, ...]:
    """Six future frames of a window and ``count`` agents' boxes in each (cars and pedestrians
    spread over the grid), as the forecast's render draws them."""
    g = torch.Generator().manual_seed(0)
    volume = torch.randint(0, 18, (steps, 200, 200, 16), generator=g, dtype=torch.uint8)
    centre = torch.rand(steps, count, 2, generator=g, dtype=torch.float64) * 80 - 40
    heading = torch.rand(steps, count, generator=g, dtype=torch.float64) * 6.28
    half = torch.tensor([2.3, 0.95], dtype=torch.float64).expand(steps, count, 2)
    boxes = torch.cat([centre, heading.cos()[..., None], heading.sin()[..., None], half], -1)
    levels = torch.tensor([[1, 6]]).expand(count, 2).contiguous()
    labels = torch.full((count,), 4, dtype=torch.uint8)
    return tuple(t.to(DEVICE) for t in (volume, boxes, levels, labels))


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_draw_boxes(benchmark, impl):
    """40 agents' boxes drawn into six 200 x 200 x 16 frames (the window of 53 x 53 columns
    around each box's centre tested, as the render does); the reference marks every covered
    voxel with its box's number and keeps the largest."""
    benchmark.group = "draw_boxes 40 boxes x 6 frames [6,200,200,16]"
    inputs = _forecast_boxes()
    # no arithmetic to speak of per voxel; bytes: the frames read and written
    benchmark.extra_info.update(flops=0.0, bytes=float(2 * inputs[0].numel()))
    benchmark.pedantic(synchronized(lambda: IMPLS[impl].draw_boxes(*inputs, (-40.0, -40.0), 0.4, 26)),
                       rounds=rounds(10), warmup_rounds=1)


def _window_fit() -> tuple:
    """The box fit of a synthetic validation window's agents: the arguments
    :func:`~t3fast.agents.boxes.fit_agent_boxes` passes :func:`t3fast.ops.box_fit`."""
    from unittest import mock

    from t3fast import ops
    from t3fast.agents import boxes
    from t3fast.data.sample import PRESENT
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.models.ego_motion import planar_poses

    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    poses = planar_poses(sample.ego_poses[None], PRESENT)[0, : PRESENT + 1].double()
    with mock.patch.object(boxes.ops, "box_fit", wraps=ops.box_fit) as spy:
        boxes.fit_agent_boxes(sample.occ[: PRESENT + 1], poses)
    return tuple(a.to(DEVICE) if isinstance(a, torch.Tensor) else a for a in spy.call_args.args)


@pytest.mark.parametrize("impl", IMPL_NAMES)
def test_box_fit(benchmark, impl):
    """One window's agents' boxes fitted (100 Adam steps on every agent's samples in six
    frames); the reference gathers the samples with tensor ops and steps them with one op
    per term (the fit as the forecast ran it before)."""
    benchmark.group = "box_fit one window's agents, 100 Adam steps"
    args = _window_fit()
    ids, track, centroid, poses, start, reach, lower, voxel, window, near, iters = args[:11]
    fitted = reach[0] > 0
    samples = IMPLS["reference"].box_fit_samples(ids[0], track[0, fitted], centroid[0, fitted], poses[0],
                                        reach[0, fitted].clamp(max=window), lower, voxel, near)["agent"].numel()
    # about 60 flops per sample and step (its margin, sigmoid and gradient row); bytes: the
    # frames' component maps read once
    benchmark.extra_info.update(flops=60.0 * samples * iters, bytes=float(ids.numel() * 8), agents=track.shape[1],
                                samples=samples)
    benchmark.pedantic(synchronized(lambda: IMPLS[impl].box_fit(*args)), rounds=rounds(10), warmup_rounds=1)
