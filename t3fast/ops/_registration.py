"""Teaches torch about the compiled kernels: fake (meta) kernels so that ``torch.compile`` can
trace the ops, and autograd formulas whose backward passes are themselves registered ops.

Higher-order gradients: ``axis_pool`` and ``delta_fuse`` are (bi)linear, so their backward ops
are differentiable too (to any order). ``triplane_decode``'s and ``matching_costs``' backward ops
are not: differentiating through them raises a ``RuntimeError`` pointing at the reference, never
a silent zero.

Imported only once :mod:`t3fast.ops._extension` has loaded the extension, which defines the
ops' schemas."""

from __future__ import annotations

from contextlib import nullcontext

import torch

ops = torch.ops.t3fast


def _check_like(op: str, ref_name: str, ref: torch.Tensor, **tensors) -> None:
    """Device and dtype agreement, checked in the fake kernels as the C++ kernels do, so that
    tracing and mixed-device calls (which dispatch to the fake kernel) fail the same way."""
    for name, t in tensors.items():
        if t is None:
            continue
        torch._check(
            t.device == ref.device,
            lambda name=name, t=t: f"t3fast.{op}: {name} must be on the same device as "
            f"{ref_name} ({ref.device}), got {t.device}",
        )
        torch._check(
            t.dtype == ref.dtype,
            lambda name=name, t=t: f"t3fast.{op}: {name} must have the dtype of {ref_name} "
            f"({ref.dtype}), got {t.dtype}",
        )


def _named(prefix: str, tensors) -> dict:
    return {f"{prefix}[{i}]": t for i, t in enumerate(tensors)}


# ---------------------------------------------------------------- triplane_decode
@torch.library.register_fake("t3fast::triplane_decode")
def _triplane_decode_fake(xy, xz, yz, weights, biases, points, grid, pe_freqs, argmax, live=None):
    torch._check(xy.dim() == 4, lambda: f"xy must have 4 dims, got {xy.dim()}")
    torch._check(len(weights) > 0, lambda: "weights must hold at least one layer")
    torch._check((points is None) != (grid is None), lambda: "exactly one of grid/points")
    _check_like("triplane_decode", "xy", xy, xz=xz, yz=yz, points=points,
                **_named("weights", weights), **_named("biases", biases))
    torch._check(live is None or (points is not None and argmax), lambda: "live needs points and argmax=True")
    torch._check(live is None or live.device == xy.device,
                 lambda: f"t3fast.triplane_decode: live must be on the same device as xy ({xy.device})")
    shape = (xy.shape[0], *grid) if grid is not None else (xy.shape[0], points.shape[1])
    if argmax:
        return xy.new_empty(shape, dtype=torch.uint8)
    return xy.new_empty((*shape, weights[-1].shape[0]))


@torch.library.register_fake("t3fast::triplane_decode_backward")
def _triplane_decode_backward_fake(grad_out, xy, xz, yz, weights, biases, points, grid, pe_freqs):
    return (
        torch.empty_like(xy),
        torch.empty_like(xz),
        torch.empty_like(yz),
        [torch.empty_like(w) for w in weights],
        [torch.empty_like(b) for b in biases],
    )


def _cuda_autocast_dtype(t: torch.Tensor) -> torch.dtype | None:
    """The dtype the CUDA kernels compute ``t``'s call in under autocast (they read the autocast
    state themselves), or None outside autocast, on the CPU and for float64."""
    if t.device.type != "cuda" or t.dtype == torch.float64 or not torch.is_autocast_enabled("cuda"):
        return None
    return torch.get_autocast_dtype("cuda")


def _triplane_decode_setup(ctx, inputs, output):
    xy, xz, yz, weights, biases, points, grid, pe_freqs, _, *live = inputs
    # the dispatcher drops a trailing argument left at its default: a gradient slot for live
    # only when it was given
    ctx.given_live = bool(live) and live[0] is not None
    ctx.layers = len(weights)
    ctx.grid = grid
    ctx.pe_freqs = pe_freqs
    # the backward runs outside the forward's autocast region: it recomputes the layers in
    # the forward's precision, as autograd runs a low-precision op's backward in its dtype
    ctx.autocast_dtype = _cuda_autocast_dtype(xy)
    ctx.save_for_backward(xy, xz, yz, points, *weights, *biases)


def _triplane_decode_backward(ctx, grad):
    xy, xz, yz, points, *params = ctx.saved_tensors
    weights, biases = params[: ctx.layers], params[ctx.layers :]
    region = nullcontext() if ctx.autocast_dtype is None else torch.autocast("cuda", dtype=ctx.autocast_dtype)
    with region:
        gxy, gxz, gyz, gw, gb = ops.triplane_decode_backward.default(
            grad, xy, xz, yz, weights, biases, points, ctx.grid, ctx.pe_freqs
        )
    # query points, the integer arguments and the live counts get no gradient
    grads = (gxy, gxz, gyz, list(gw), list(gb), None, None, None, None)
    return grads + (None,) * ctx.given_live


torch.library.register_autograd(
    "t3fast::triplane_decode", _triplane_decode_backward, setup_context=_triplane_decode_setup
)

DOUBLE_BACKWARD_UNSUPPORTED = (
    "t3fast.triplane_decode: double backward is not supported; use "
    "t3fast.ops.reference.triplane_decode for higher-order gradients (torch 2.12 or later)"
)


def _no_setup(ctx, inputs, output):
    pass


def _triplane_decode_double_backward(ctx, *grads):
    # Reached only when a gradient of the first backward is itself differentiated (e.g.
    # create_graph=True and a gradient penalty): torch's fallback would return zeros.
    raise RuntimeError(DOUBLE_BACKWARD_UNSUPPORTED)


torch.library.register_autograd(
    "t3fast::triplane_decode_backward", _triplane_decode_double_backward, setup_context=_no_setup
)


# ---------------------------------------------------------------- axis_pool
@torch.library.register_fake("t3fast::axis_pool")
def _axis_pool_fake(volume):
    torch._check(volume.dim() == 5, lambda: f"volume must have 5 dims, got {volume.dim()}")
    b, c, x, y, z = volume.shape
    return volume.new_empty((b, c, x, y)), volume.new_empty((b, c, x, z)), volume.new_empty(
        (b, c, y, z)
    )


@torch.library.register_fake("t3fast::axis_pool_backward")
def _axis_pool_backward_fake(grad_xy, grad_xz, grad_yz):
    b, c, x, y = grad_xy.shape
    return grad_xy.new_empty((b, c, x, y, grad_xz.shape[3]))


def _axis_pool_setup(ctx, inputs, output):
    pass


def _axis_pool_backward(ctx, grad_xy, grad_xz, grad_yz):
    return ops.axis_pool_backward.default(grad_xy, grad_xz, grad_yz)


torch.library.register_autograd(
    "t3fast::axis_pool", _axis_pool_backward, setup_context=_axis_pool_setup
)


def _axis_pool_backward_backward(ctx, grad_volume):
    # the backward is the adjoint of the (linear) forward, so its own adjoint is the forward
    return ops.axis_pool.default(grad_volume)


torch.library.register_autograd(
    "t3fast::axis_pool_backward", _axis_pool_backward_backward, setup_context=_no_setup
)


# ---------------------------------------------------------------- delta_fuse
@torch.library.register_fake("t3fast::delta_fuse")
def _delta_fuse_fake(delta, prev, weight, bias):
    torch._check(delta.dim() == 4, lambda: f"delta must have 4 dims, got {delta.dim()}")
    _check_like("delta_fuse", "delta", delta, prev=prev, weight=weight, bias=bias)
    return torch.empty_like(delta, memory_format=torch.contiguous_format)


@torch.library.register_fake("t3fast::delta_fuse_backward")
def _delta_fuse_backward_fake(grad_out, prev, weight):
    return (
        torch.empty_like(prev, memory_format=torch.contiguous_format),
        torch.empty_like(weight),
        weight.new_empty((weight.shape[0],)),
    )


def _delta_fuse_setup(ctx, inputs, output):
    _, prev, weight, bias = inputs
    ctx.has_bias = bias is not None
    ctx.save_for_backward(prev, weight)


def _delta_fuse_backward(ctx, grad):
    prev, weight = ctx.saved_tensors
    grad_prev, grad_weight, grad_bias = ops.delta_fuse_backward.default(grad, prev, weight)
    return grad, grad_prev, grad_weight, grad_bias if ctx.has_bias else None


torch.library.register_autograd(
    "t3fast::delta_fuse", _delta_fuse_backward, setup_context=_delta_fuse_setup
)


def _delta_fuse_backward_setup(ctx, inputs, output):
    ctx.save_for_backward(*inputs)


def _delta_fuse_backward_backward(ctx, gg_prev, gg_weight, gg_bias):
    """Gradients of (grad_prev = W^T g, grad_weight = sum g prev^T, grad_bias = sum g), which are
    bilinear in (g, prev, W), with respect to g, prev and W; in plain torch ops, so that every
    further order is differentiable as well."""
    grad, prev, weight = ctx.saved_tensors
    grad_grad = torch.zeros_like(grad)
    grad_prev = grad_weight = None
    if gg_prev is not None:
        grad_grad = grad_grad + torch.einsum("oc,bchw->bohw", weight, gg_prev)
        grad_weight = torch.einsum("bohw,bchw->oc", grad, gg_prev)
    if gg_weight is not None:
        grad_grad = grad_grad + torch.einsum("oc,bchw->bohw", gg_weight, prev)
        grad_prev = torch.einsum("oc,bohw->bchw", gg_weight, grad)
    if gg_bias is not None:
        grad_grad = grad_grad + gg_bias[None, :, None, None]
    return grad_grad, grad_prev, grad_weight


torch.library.register_autograd(
    "t3fast::delta_fuse_backward", _delta_fuse_backward_backward, setup_context=_delta_fuse_backward_setup
)


# ---------------------------------------------------------------- matching_costs
@torch.library.register_fake("t3fast::matching_costs")
def _matching_costs_fake(present, previous, radius):
    torch._check(present.dim() == 4, lambda: f"present must have 4 dims, got {present.dim()}")
    _check_like("matching_costs", "present", present, previous=previous)
    torch._check(previous.shape == present.shape,
                 lambda: f"t3fast.matching_costs: previous must have the shape of present {list(present.shape)}, "
                 f"got {list(previous.shape)}")
    b, _, h, w = present.shape
    return present.new_empty((b, (2 * radius + 1) ** 2, h, w))


@torch.library.register_fake("t3fast::matching_costs_backward")
def _matching_costs_backward_fake(grad, present, previous, radius):
    _check_like("matching_costs_backward", "present", present, grad=grad, previous=previous)
    return torch.empty_like(present), torch.empty_like(previous)


def _matching_costs_setup(ctx, inputs, output):
    present, previous, ctx.radius = inputs
    ctx.save_for_backward(present, previous)


def _matching_costs_backward(ctx, grad):
    present, previous = ctx.saved_tensors
    grad_present, grad_previous = ops.matching_costs_backward.default(grad, present, previous, ctx.radius)
    return grad_present, grad_previous, None


torch.library.register_autograd("t3fast::matching_costs", _matching_costs_backward,
                                setup_context=_matching_costs_setup)


def _matching_costs_double_backward(ctx, *grads):
    raise RuntimeError("t3fast.matching_costs: double backward is not supported; use "
                       "t3fast.ops.reference.matching_costs for higher-order gradients")


torch.library.register_autograd("t3fast::matching_costs_backward", _matching_costs_double_backward,
                                setup_context=_no_setup)


# ---------------------------------------------------------------- group_norm_silu
def _group_norm_silu_check(op, input, weight, bias, residual, groups):
    torch._check(input.dim() >= 2, lambda: f"t3fast.{op}: input must have at least 2 dims [B, C, *], got "
                 f"{input.dim()} dims {list(input.shape)}")
    _check_like(op, "input", input, weight=weight, bias=bias, residual=residual)
    torch._check(groups >= 1 and input.shape[1] % groups == 0,
                 lambda: f"t3fast.{op}: groups must be a positive divisor of the {input.shape[1]} channels, "
                 f"got {groups}")


def _statistics_dtype(input: torch.Tensor) -> torch.dtype:
    return torch.float64 if input.dtype == torch.float64 else torch.float32


@torch.library.register_fake("t3fast::group_norm_silu")
def _group_norm_silu_fake(input, weight, bias, groups, eps, residual=None):
    _group_norm_silu_check("group_norm_silu", input, weight, bias, residual, groups)
    stats = input.new_empty((input.shape[0], groups), dtype=_statistics_dtype(input))
    return torch.empty_like(input, memory_format=torch.contiguous_format), stats, torch.empty_like(stats)


@torch.library.register_fake("t3fast::group_norm_silu_backward")
def _group_norm_silu_backward_fake(grad, input, weight, bias, residual, mean, rstd, groups):
    _group_norm_silu_check("group_norm_silu_backward", input, weight, bias, residual, groups)
    _check_like("group_norm_silu_backward", "input", input, grad=grad)
    contiguous = torch.contiguous_format
    grad_residual = (torch.empty_like(residual, memory_format=contiguous) if residual is not None
                     else input.new_empty((0,)))
    return (torch.empty_like(input, memory_format=contiguous), torch.empty_like(weight, memory_format=contiguous),
            torch.empty_like(bias, memory_format=contiguous), grad_residual)


def _group_norm_silu_setup(ctx, inputs, output):
    input, weight, bias, ctx.groups, _, residual = inputs
    _, mean, rstd = output
    ctx.mark_non_differentiable(mean, rstd)  # statistics for the backward, not results
    ctx.has_residual = residual is not None
    ctx.save_for_backward(input, weight, bias, residual, mean, rstd)


def _group_norm_silu_backward(ctx, grad, _grad_mean, _grad_rstd):
    input, weight, bias, residual, mean, rstd = ctx.saved_tensors
    grad_input, grad_weight, grad_bias, grad_residual = ops.group_norm_silu_backward.default(
        grad, input, weight, bias, residual, mean, rstd, ctx.groups)
    return grad_input, grad_weight, grad_bias, None, None, grad_residual if ctx.has_residual else None


torch.library.register_autograd("t3fast::group_norm_silu", _group_norm_silu_backward,
                                setup_context=_group_norm_silu_setup)


def _group_norm_silu_double_backward(ctx, *grads):
    raise RuntimeError("t3fast.group_norm_silu: double backward is not supported; use "
                       "t3fast.ops.reference.group_norm_silu for higher-order gradients")


torch.library.register_autograd("t3fast::group_norm_silu_backward", _group_norm_silu_double_backward,
                                setup_context=_no_setup)


# ---------------------------------------------------------------- label_conv3d
@torch.library.register_fake("t3fast::label_conv3d")
def _label_conv3d_fake(labels, table):
    torch._check(labels.dim() == 4, lambda: f"labels must have 4 dims, got {labels.dim()}")
    torch._check(table.dim() == 3, lambda: f"table must have 3 dims, got {table.dim()}")
    torch._check(
        table.device == labels.device,
        lambda: f"t3fast.label_conv3d: table must be on the same device as labels ({labels.device}), "
        f"got {table.device}",
    )
    return table.new_empty((labels.shape[0], table.shape[2], *labels.shape[1:]))


def _label_conv3d_setup(ctx, inputs, output):
    labels, table = inputs
    ctx.classes = table.shape[1]
    ctx.save_for_backward(labels)


def _label_conv3d_backward(ctx, grad):
    (labels,) = ctx.saved_tensors
    return None, ops.label_conv3d_backward.default(grad, labels, ctx.classes)


torch.library.register_autograd("t3fast::label_conv3d", _label_conv3d_backward, setup_context=_label_conv3d_setup)


@torch.library.register_fake("t3fast::label_conv3d_backward")
def _label_conv3d_backward_fake(grad, labels, classes):
    torch._check(grad.dim() == 5, lambda: f"grad must have 5 dims, got {grad.dim()}")
    return grad.new_empty((27, classes, grad.shape[1]))


def _label_conv3d_backward_setup(ctx, inputs, output):
    _, labels, _ = inputs
    ctx.save_for_backward(labels)


def _label_conv3d_backward_backward(ctx, grad_table):
    """The table gradient is linear in the output gradient: its own gradient is the forward."""
    (labels,) = ctx.saved_tensors
    return ops.label_conv3d.default(labels, grad_table), None, None


torch.library.register_autograd("t3fast::label_conv3d_backward", _label_conv3d_backward_backward,
                                setup_context=_label_conv3d_backward_setup)


# ---------------------------------------------------------------- bev_components
@torch.library.register_fake("t3fast::bev_components")
def _bev_components_fake(mask):
    torch._check(mask.dim() == 3, lambda: f"mask must have 3 dims, got {mask.dim()}")
    return mask.new_empty(mask.shape, dtype=torch.long), mask.new_empty(mask.shape[:1], dtype=torch.long)


# ---------------------------------------------------------------- draw_boxes
@torch.library.register_fake("t3fast::draw_boxes")
def _draw_boxes_fake(volume, boxes, levels, labels, lower, voxel_size, reach):
    torch._check(volume.dim() == 4, lambda: f"volume must have 4 dims, got {volume.dim()}")
    _check_like("draw_boxes", "volume", volume, labels=labels)
    return torch.empty_like(volume, memory_format=torch.contiguous_format)


# ---------------------------------------------------------------- box_fit
@torch.library.register_fake("t3fast::box_fit")
def _box_fit_fake(ids, track, centroid, poses, start, reach, lower, voxel_size, window, near, iters, lr, softness,
                  accel_prior):
    torch._check(start.dim() == 3, lambda: f"start must have 3 dims, got {start.dim()}")
    for name, t in (("track", track), ("centroid", centroid), ("poses", poses), ("start", start), ("reach", reach)):
        torch._check(t.device == ids.device,
                     lambda name=name, t=t: f"t3fast.box_fit: {name} must be on the same device as ids "
                     f"({ids.device}), got {t.device}")
    return torch.empty_like(start, memory_format=torch.contiguous_format), start.new_empty(start.shape[:2])


# ---------------------------------------------------------------- autocast
_autocast_lib = torch.library.Library("t3fast", "IMPL")


def _register_autocast(op: str, device_type: str, float32: bool = False) -> None:
    """``op`` under autocast on ``device_type``: its floating inputs other than float64 cast to
    the autocast dtype on CUDA (as ``conv2d`` runs, whose 1x1 case ``delta_fuse`` fuses), to
    float32 on the CPU, whose kernels have no lower precision, and everywhere for ``float32``
    ops (normalisations, which autocast runs in float32); so that a tensor from an autocast
    layer meets float32 planes and weights in one dtype."""
    key = "Autocast" + torch._C._dispatch_key_for_device(device_type)
    excluded = torch._C.DispatchKeySet(getattr(torch._C.DispatchKey, key))
    overload = getattr(ops, op).default

    def kernel(_keyset, *args):
        dtype = torch.get_autocast_dtype(device_type) if device_type == "cuda" and not float32 else torch.float32

        def cast(a):
            if isinstance(a, list | tuple):
                return [cast(t) for t in a]
            if isinstance(a, torch.Tensor) and a.is_floating_point() and a.dtype != torch.float64:
                return a.to(dtype)
            return a

        with torch._C._ExcludeDispatchKeyGuard(excluded):
            return overload(*(cast(a) for a in args))

    _autocast_lib.impl(op, kernel, key, with_keyset=True)


# On CUDA only delta_fuse mixes an autocast output with float32 parameters: the decoder casts
# its planes itself (it decodes in its weights' dtype) and axis_pool reads one tensor;
# group_norm_silu computes in float32 everywhere, as group_norm under CUDA's autocast. The CUDA
# triplane_decode has no autocast kernel: it reads the autocast dtype and runs its MLP in it,
# keeping the planes and query points in their own precision (as grid_sample, which autocast
# runs in float32).
for _op, _device_type in (("delta_fuse", "cuda"), ("delta_fuse", "cpu"), ("axis_pool", "cpu"),
                          ("triplane_decode", "cpu"), ("label_conv3d", "cpu")):
    _register_autocast(_op, _device_type)
for _device_type in ("cuda", "cpu"):
    _register_autocast("group_norm_silu", _device_type, float32=True)
