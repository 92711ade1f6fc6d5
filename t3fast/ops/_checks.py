"""Argument checks made in Python.

* Those the C++ glue cannot make: Python integers too large for int64, and outputs too large
  for the device, refused with a message instead of a cast error or an allocator failure.
* Without the compiled extension, the C++ glue's own checks (csrc/checks.h,
  csrc/triplane_args.cpp), with the same messages, so that the references the ops then run
  through fail as clearly as the kernels would.
"""

from __future__ import annotations

import math
import operator
import os
from collections.abc import Sequence

import torch


def device_memory_bytes(device: torch.device) -> int | None:
    """Total memory of ``device`` (physical RAM for the CPU); None where it cannot be told."""
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory
    if device.type == "cpu" and hasattr(os, "sysconf"):
        try:
            return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError):
            return None
    return None


def _human(nbytes: int) -> str:
    size = float(nbytes)
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if size < 1024 or unit == "PB":
            return f"{size:.1f} {unit}"
        size /= 1024
    raise AssertionError("unreachable")


def checked_grid(grid: Sequence[int], xy: torch.Tensor, classes: int, argmax: bool) -> list[int]:
    """``grid`` as ints after checking that the full-grid output fits in memory.

    The output holds ``B * X * Y * Z`` uint8 labels (``argmax``) or ``B * X * Y * Z * classes``
    values of ``xy``'s dtype.
    """
    try:
        sizes = [operator.index(n) for n in grid]
    except TypeError:
        raise ValueError(f"t3fast.triplane_decode: grid must hold integers, got {tuple(grid)!r}") from None
    if any(abs(n) >= 2**63 for n in sizes):
        raise ValueError(f"t3fast.triplane_decode: grid sizes must fit in 64 bits, got {tuple(sizes)}")
    if len(sizes) != 3 or any(n < 0 for n in sizes):
        return sizes  # the compiled op names these mistakes
    if torch.compiler.is_compiling():
        return sizes  # the memory query cannot be traced; eager calls check it
    per_voxel = 1 if argmax else classes * xy.element_size()
    nbytes = xy.shape[0] * sizes[0] * sizes[1] * sizes[2] * per_voxel
    limit = device_memory_bytes(xy.device)
    if limit is not None and nbytes > limit:
        what = "labels" if argmax else f"logits of {classes} classes"
        raise ValueError(
            f"t3fast.triplane_decode: grid {tuple(sizes)} at batch {xy.shape[0]} needs {_human(nbytes)} of "
            f"{what}, more than the {_human(limit)} of memory on {xy.device}"
        )
    return sizes


# ---------------------------------------------------------------- the C++ glue's checks
def _require(ok: bool, op: str, message: str) -> None:
    if not ok:
        raise RuntimeError(f"t3fast.{op}: {message}")


def _dtype_name(dtype: torch.dtype) -> str:
    """The name the C++ messages give a dtype: torch.float64 -> "Double"."""
    return torch.empty(0, dtype=dtype).type().removeprefix("torch.").removesuffix("Tensor")


def _check_dim(t: torch.Tensor, op: str, name: str, dim: int, layout: str) -> None:
    _require(t.dim() == dim, op, f"{name} must have {dim} dims {layout}, got {t.dim()} dims {list(t.shape)}")


def _check_size(t: torch.Tensor, op: str, name: str, d: int, expected: int, what: str) -> None:
    _require(t.shape[d] == expected, op,
             f"{name}.shape[{d}] ({what}) must be {expected}, got {t.shape[d]} (shape {list(t.shape)})")


def _check_device(t: torch.Tensor, ref: torch.Tensor, op: str, name: str, ref_name: str) -> None:
    _require(t.device == ref.device, op,
             f"{name} must be on the same device as {ref_name} ({ref.device}), got {t.device}")


def _check_dtype(t: torch.Tensor, ref: torch.Tensor, op: str, name: str, ref_name: str) -> None:
    _require(t.dtype == ref.dtype, op, f"{name} must have the dtype of {ref_name} "
             f"({_dtype_name(ref.dtype)}), got {_dtype_name(t.dtype)}")


def _check_like(t: torch.Tensor, ref: torch.Tensor, op: str, name: str, ref_name: str) -> None:
    _check_device(t, ref, op, name, ref_name)
    _check_dtype(t, ref, op, name, ref_name)


def _check_float(t: torch.Tensor, op: str, name: str) -> None:
    """The floating dtypes the kernels take: float32/float64, on CUDA also float16/bfloat16."""
    if t.is_cuda:
        _require(t.dtype in (torch.float32, torch.float64, torch.float16, torch.bfloat16), op,
                 f"{name} must be float32, float64, float16 or bfloat16 on CUDA, got {_dtype_name(t.dtype)}")
    else:
        _require(t.dtype in (torch.float32, torch.float64), op,
                 f"{name} must be float32 or float64 on CPU, got {_dtype_name(t.dtype)}")


def check_triplane_decode(xy, xz, yz, weights, biases, points, grid, pe_freqs: int, argmax: bool,
                          live=None) -> None:
    """triplane_decode's arguments, as csrc/triplane_args.cpp checks them."""
    op = "triplane_decode"
    _check_dim(xy, op, "xy", 4, "[B, C, X', Y']")
    _check_dim(xz, op, "xz", 4, "[B, C, X', Z']")
    _check_dim(yz, op, "yz", 4, "[B, C, Y', Z']")
    _check_float(xy, op, "xy")
    _check_like(xz, xy, op, "xz", "xy")
    _check_like(yz, xy, op, "yz", "xy")
    _check_size(xz, op, "xz", 0, xy.shape[0], "batch, as xy")
    _check_size(yz, op, "yz", 0, xy.shape[0], "batch, as xy")
    _check_size(xz, op, "xz", 1, xy.shape[1], "channels, as xy")
    _check_size(yz, op, "yz", 1, xy.shape[1], "channels, as xy")
    _check_size(xz, op, "xz", 2, xy.shape[2], "X', as xy.shape[2]")
    _check_size(yz, op, "yz", 2, xy.shape[3], "Y', as xy.shape[3]")
    _check_size(yz, op, "yz", 3, xz.shape[3], "Z', as xz.shape[3]")
    _require(xy.shape[1] > 0, op, f"planes must have at least one channel, got xy {list(xy.shape)}")
    _require(all(p.shape[2] > 0 and p.shape[3] > 0 for p in (xy, xz, yz)), op,
             f"planes must have non-empty spatial dims, got xy {list(xy.shape)}, xz {list(xz.shape)}, "
             f"yz {list(yz.shape)}")

    _require((points is None) != (grid is None), op, "exactly one of grid and points must be given, got "
             + ("both" if points is not None else "neither"))
    _require(0 <= pe_freqs <= 30, op, f"pe_freqs must be in [0, 30], got {pe_freqs}")
    if points is not None:
        _check_dim(points, op, "points", 3, "[B, N, 3]")
        _check_size(points, op, "points", 0, xy.shape[0], "batch, as xy")
        _check_size(points, op, "points", 2, 3, "coordinates (x, y, z)")
        _check_like(points, xy, op, "points", "xy")
    else:
        _require(len(grid) == 3, op, f"grid must be (X, Y, Z), got {len(grid)} values {list(grid)}")
        _require(all(n >= 0 for n in grid), op, f"grid sizes must be >= 0, got {list(grid)}")

    _require(len(weights) > 0, op, "weights must hold at least one layer, got none")
    _require(len(weights) == len(biases), op, "weights and biases must have the same number of layers, "
             f"got {len(weights)} weights and {len(biases)} biases")
    width = xy.shape[1] + 6 * pe_freqs
    for i, (w, b) in enumerate(zip(weights, biases)):
        _check_like(w, xy, op, f"weights[{i}]", "xy")
        _check_like(b, xy, op, f"biases[{i}]", "xy")
        _check_dim(w, op, f"weights[{i}]", 2, "[out, in]")
        _check_dim(b, op, f"biases[{i}]", 1, "[out]")
        source = "C + 6 * pe_freqs" if i == 0 else "the previous layer's out features"
        _require(w.shape[1] == width, op, f"weights[{i}].shape[1] (in features) must be {width} ({source}), "
                 f"got {w.shape[1]} (shape {list(w.shape)})")
        _require(b.shape[0] == w.shape[0], op,
                 f"biases[{i}].shape[0] must be {w.shape[0]} (weights[{i}].shape[0]), got {b.shape[0]}")
        width = w.shape[0]
    if live is not None:
        _require(points is not None and argmax, op, "live counts the points to decode: it needs points and argmax=True")
        _check_device(live, xy, op, "live", "xy")
        _require(live.dtype == torch.int64, op, f"live must be int64, got {_dtype_name(live.dtype)}")
        _require(live.dim() == 1 and live.shape[0] == xy.shape[0], op,
                 f"live must be [B] = [{xy.shape[0]}] (one count per batch element), got {list(live.shape)}")
    _require(not argmax or 1 <= width <= 256, op,
             f"argmax=True needs 1 to 256 classes (uint8 labels), got {width}")


def check_axis_pool(volume: torch.Tensor) -> None:
    """axis_pool's argument, as csrc/checks.h checks it."""
    op = "axis_pool"
    _check_dim(volume, op, "volume", 5, "[B, C, X, Y, Z]")
    _check_float(volume, op, "volume")
    _require(all(n > 0 for n in volume.shape[2:]), op,
             f"volume must have non-empty X, Y, Z, got {list(volume.shape)}")


def check_delta_fuse(delta: torch.Tensor, prev: torch.Tensor, weight: torch.Tensor,
                     bias: torch.Tensor | None) -> None:
    """delta_fuse's arguments, as csrc/checks.h checks them."""
    op = "delta_fuse"
    _check_dim(delta, op, "delta", 4, "[B, C, H, W]")
    _check_dim(prev, op, "prev", 4, "[B, C_in, H, W]")
    _check_dim(weight, op, "weight", 2, "[C, C_in]")
    _check_float(delta, op, "delta")
    # devices first: the compiled op reports a mixed-device call from its fake kernel, which
    # compares prev with delta; its C++ checks then compare weight's dtype with prev's first
    _check_device(prev, delta, op, "prev", "delta")
    _check_device(weight, prev, op, "weight", "prev")
    _check_dtype(weight, prev, op, "weight", "prev")
    _check_dtype(prev, delta, op, "prev", "delta")
    _check_size(weight, op, "weight", 1, prev.shape[1], "C_in, as prev.shape[1]")
    _check_size(prev, op, "prev", 0, delta.shape[0], "batch, as delta")
    _check_size(prev, op, "prev", 2, delta.shape[2], "H, as delta")
    _check_size(prev, op, "prev", 3, delta.shape[3], "W, as delta")
    _check_size(weight, op, "weight", 0, delta.shape[1], "C, as delta.shape[1]")
    if bias is not None:
        _check_dim(bias, op, "bias", 1, "[C]")
        _check_like(bias, delta, op, "bias", "delta")
        _check_size(bias, op, "bias", 0, delta.shape[1], "C, as delta.shape[1]")


def check_matching_costs(present: torch.Tensor, previous: torch.Tensor, radius: int) -> None:
    """matching_costs' arguments, as csrc/checks.h checks them."""
    op = "matching_costs"
    _check_dim(present, op, "present", 4, "[B, C, H, W]")
    _check_dim(previous, op, "previous", 4, "[B, C, H, W]")
    _check_float(present, op, "present")
    _check_like(previous, present, op, "previous", "present")
    _require(previous.shape == present.shape, op,
             f"previous must have the shape of present {list(present.shape)}, got {list(previous.shape)}")
    _require(present.shape[1] > 0, op, "present must have at least one channel (the costs are channel means), "
             f"got shape {list(present.shape)}")
    _require(0 <= radius <= 64, op, f"radius must be in [0, 64], got {radius}")


def check_group_norm_silu(input: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, groups: int, eps: float,
                          residual: torch.Tensor | None) -> None:
    """group_norm_silu's arguments, as csrc/checks.h checks them."""
    op = "group_norm_silu"
    _require(input.dim() >= 2, op, f"input must have at least 2 dims [B, C, *], got {input.dim()} dims "
             f"{list(input.shape)}")
    _check_float(input, op, "input")
    for name, t in (("weight", weight), ("bias", bias)):
        _check_dim(t, op, name, 1, "[C]")
        _check_like(t, input, op, name, "input")
        _check_size(t, op, name, 0, input.shape[1], "C, as input.shape[1]")
    channels = input.shape[1]
    _require(groups >= 1 and channels % groups == 0, op,
             f"groups must be a positive divisor of the {channels} channels, got {groups}")
    _require(eps >= 0 and math.isfinite(eps), op, f"eps must be finite and >= 0, got {eps}")
    if residual is not None:
        _check_like(residual, input, op, "residual", "input")
        _require(residual.shape == input.shape, op,
                 f"residual must have the shape of input {list(input.shape)}, got {list(residual.shape)}")


def check_label_conv3d(labels: torch.Tensor, table: torch.Tensor) -> None:
    """label_conv3d's arguments, as csrc/checks.h checks them (and the CPU kernel the labels)."""
    op = "label_conv3d"
    _check_dim(labels, op, "labels", 4, "[B, X, Y, Z]")
    _require(labels.dtype in (torch.uint8, torch.int32, torch.int64), op,
             f"labels must be uint8, int32 or int64 class ids, got {_dtype_name(labels.dtype)}")
    _check_dim(table, op, "table", 3, "[27, K, C]")
    _check_float(table, op, "table")
    _check_device(table, labels, op, "table", "labels")
    _check_size(table, op, "table", 0, 27, "the 3 x 3 x 3 taps")
    _require(table.shape[1] > 0, op, f"table must hold at least one class, got {list(table.shape)}")
    if labels.numel() and not labels.is_cuda:  # the CUDA kernel does not check (no host sync)
        bad = labels[(labels < 0) | (labels >= table.shape[1])]
        if bad.numel():
            _require(False, op, f"labels must be class ids in [0, {table.shape[1]}) (the rows of table), "
                                f"got {bad[0].item()}")


def check_bev_components(mask: torch.Tensor) -> None:
    """bev_components' mask, as csrc/checks.h checks it."""
    op = "bev_components"
    _check_dim(mask, op, "mask", 3, "[B, X, Y]")
    _require(mask.dtype == torch.bool, op, f"mask must be bool, got {_dtype_name(mask.dtype)}")


def _check_grid_frame(lower: Sequence[float], voxel_size: float, op: str) -> None:
    """The columns of a label grid in metres: its lower x, y and metres per column."""
    _require(len(lower) == 2, op, f"lower must hold the grid's lower x and y, got {len(lower)} values")
    _require(voxel_size > 0, op, f"voxel_size must be positive, got {voxel_size}")


def check_draw_boxes(volume: torch.Tensor, boxes: torch.Tensor, levels: torch.Tensor, labels: torch.Tensor,
                     lower: Sequence[float], voxel_size: float, reach: int) -> None:
    """draw_boxes' arguments, as csrc/checks.h checks them."""
    op = "draw_boxes"
    _check_dim(volume, op, "volume", 4, "[B, X, Y, Z]")
    _require(volume.dtype == torch.uint8, op, f"volume must be uint8 labels, got {_dtype_name(volume.dtype)}")
    _check_dim(boxes, op, "boxes", 3, "[B, M, 6]")
    _require(boxes.dtype == torch.float64, op, f"boxes must be float64, got {_dtype_name(boxes.dtype)}")
    _check_size(boxes, op, "boxes", 0, volume.shape[0], "batch, as volume")
    _check_size(boxes, op, "boxes", 2, 6, "x, y, cos, sin, half length, half width")
    _require(levels.dim() in (2, 3), op, "levels must have 2 dims [M, 2] (every volume's) or 3 dims [B, M, 2] "
             f"(each volume's), got {levels.dim()} dims {list(levels.shape)}")
    _require(levels.dtype == torch.int64, op, f"levels must be int64, got {_dtype_name(levels.dtype)}")
    per_volume = levels.dim() == 3
    d = int(per_volume)
    if per_volume:
        _check_size(levels, op, "levels", 0, volume.shape[0], "batch, as volume")
    _check_size(levels, op, "levels", d, boxes.shape[1], "boxes, as boxes.shape[1]")
    _check_size(levels, op, "levels", d + 1, 2, "bottom, top")
    form = " dims [B, M], as levels is each volume's" if per_volume else " dim [M], as levels is every volume's"
    _require(labels.dim() == levels.dim() - 1, op,
             f"labels must have {levels.dim() - 1}{form}, got {labels.dim()} dims {list(labels.shape)}")
    _require(labels.dtype == torch.uint8, op, f"labels must be uint8, got {_dtype_name(labels.dtype)}")
    if per_volume:
        _check_size(labels, op, "labels", 0, volume.shape[0], "batch, as volume")
    _check_size(labels, op, "labels", d, boxes.shape[1], "boxes, as boxes.shape[1]")
    for name, t in (("boxes", boxes), ("levels", levels), ("labels", labels)):
        _check_device(t, volume, op, name, "volume")
    _check_grid_frame(lower, voxel_size, op)
    _require(reach >= 0, op, f"reach must be at least 0, got {reach}")


def check_box_fit(ids, track, centroid, poses, start, reach, lower, voxel_size, window, near, iters, lr, softness,
                  accel_prior) -> None:
    """box_fit's arguments, as csrc/checks.h checks them."""
    op = "box_fit"
    _check_dim(ids, op, "ids", 4, "[B, T, X, Y]")
    _require(ids.dtype == torch.int64, op, f"ids must be int64, got {_dtype_name(ids.dtype)}")
    _check_dim(track, op, "track", 3, "[B, n, T]")
    _require(track.dtype == torch.int64, op, f"track must be int64, got {_dtype_name(track.dtype)}")
    _check_size(track, op, "track", 0, ids.shape[0], "batch, as ids")
    _check_size(track, op, "track", 2, ids.shape[1], "frames, as ids.shape[1]")
    b, n, frames = ids.shape[0], track.shape[1], ids.shape[1]
    for name, t, layout, shape in (("centroid", centroid, "[B, n, T, 2]", [b, n, frames, 2]),
                                   ("poses", poses, "[B, T, 3]", [b, frames, 3]),
                                   ("start", start, "[B, n, 7]", [b, n, 7]), ("reach", reach, "[B, n]", [b, n])):
        _check_dim(t, op, name, len(shape), layout)
        _require(t.dtype == torch.float64, op, f"{name} must be float64, got {_dtype_name(t.dtype)}")
        _require(list(t.shape) == shape, op, f"{name} must be {layout} = {shape} (ids {list(ids.shape)}, track "
                 f"{list(track.shape)}), got {list(t.shape)}")
        _check_device(t, ids, op, name, "ids")
    _check_device(track, ids, op, "track", "ids")
    _check_grid_frame(lower, voxel_size, op)
    _require(0 <= window <= 1024, op, f"window must be in [0, 1024] cells, got {window}")
    _require(0 <= near <= 16, op, f"near must be in [0, 16] cells, got {near}")
    _require(iters >= 0, op, f"iters must be at least 0, got {iters}")
    _require(lr > 0, op, f"lr must be positive, got {lr}")
    _require(len(softness) == 2 and softness[0] > 0 and softness[1] > 0, op,
             f"softness must hold two positive widths (first and last iteration), got {list(softness)}")
