"""The checks :meth:`~t3fast.models.world_model.T3Former.forecast` runs on its arguments.

Every refusal is a :class:`~t3fast.errors.UsageError` (a ``ValueError``) whose one-line
message names the argument, the first offending index and what is accepted, raised before
any frame is encoded. Motion is bounded to what driving can do: an ego moves at most
:data:`MAX_STEP_METRES` between two frames and stands at most :data:`MAX_WORLD_METRES` from the
origin of its world frame; beyond those, poses and displacements are not a vehicle's
(a 1e30 m step makes the planned trajectory NaN and every future frame free).

The checks of values (class ids, finite, bounded, rigid) compute on the device whether they
pass; under :func:`read_together` (as :meth:`~t3fast.models.world_model.T3Former.forecast` runs
them) they are read back in one host synchronisation, the first that fails raising as if each
had been read on its own. They are skipped inside ``torch.compile`` graphs and CUDA graph
capture, where a read-back would break the graph: eager calls check.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import torch
from torch import Tensor, nn

from t3fast.data.classes import IGNORE
from t3fast.data.route import COMMANDS
from t3fast.device_constants import device_constant
from t3fast.errors import UsageError
from t3fast.models.flow_forecaster import FlowTriplaneForecaster
from t3fast.models.planner import MotionPlanner
from t3fast.models.route_planner import RoutePlanner

#: The longest ego step between two frames, in metres: 720 km/h at the 2 Hz of the frames.
MAX_STEP_METRES = 100.0
#: The farthest an ego -> world pose may place the ego from the world origin, in metres: map,
#: UTM and Earth-centred frames all stay within it.
MAX_WORLD_METRES = 1e7
#: How far a pose's rotation block may be from orthonormal (and its last row from 0, 0, 0, 1):
#: float32 round-off is ~1e-7.
RIGID_TOLERANCE = 1e-3

# metres per frame at 2 Hz to km/h: x 2 frames a second x 3.6
_STEP_LIMIT = f"at most {MAX_STEP_METRES:g} m per frame ({MAX_STEP_METRES * 7.2:g} km/h at 2 Hz) is accepted"


def can_read_values(values: Tensor) -> bool:
    """Whether a check may read ``values`` back: not while ``torch.compile`` traces a graph or
    a CUDA graph is being captured, nor from the meta device (shapes without values)."""
    if torch.compiler.is_compiling() or values.device.type == "meta":
        return False
    return not (values.is_cuda and torch.cuda.is_current_stream_capturing())


_pending: list[list[tuple[Tensor, Callable[[], None]]]] = []


@contextmanager
def read_together() -> Iterator[None]:
    """The value checks run inside are read back together when it closes, in one host
    synchronisation; the first of them that fails then raises its own message."""
    pending: list[tuple[Tensor, Callable[[], None]]] = []
    _pending.append(pending)
    try:
        yield
    finally:
        _pending.pop()
    if pending:
        passed = torch.stack([ok.reshape(()) for ok, _ in pending])
        if bool(passed.all()):  # the one read when all is well
            return
        for ok, (_, fail) in zip(passed.tolist(), pending):
            if not ok:
                fail()


def _require(ok: Tensor, fail: Callable[[], None]) -> None:
    """``fail()`` (which raises) unless ``ok`` (a bool tensor on the device) holds: read now, or
    with the other checks when :func:`read_together` closes."""
    if _pending:
        _pending[-1].append((ok, fail))
    elif not bool(ok):
        fail()


def _index(mask: Tensor) -> tuple[int, ...]:
    """The index of the first True entry of a boolean tensor."""
    return tuple(mask.nonzero()[0].tolist())


def _at(name: str, index: tuple[int, ...]) -> str:
    """``name[i, j]``: an entry of an argument, for a message."""
    return f"{name}[{', '.join(map(str, index))}]"


def check_tensor(name: str, value: Any, floating: bool = True) -> None:
    """``value`` must be a tensor, of a floating-point dtype when ``floating`` (metres and
    radians: integers and booleans are not motion)."""
    if not isinstance(value, Tensor):
        raise UsageError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if floating and not value.is_floating_point():
        raise UsageError(f"{name} must be a floating-point tensor (metres), got {value.dtype}")


def check_finite(name: str, values: Tensor) -> None:
    """Raises :class:`UsageError` naming ``name`` and the index of its first NaN or infinity (a
    non-finite pose or displacement would make the whole forecast NaN)."""
    if not values.is_floating_point() or not can_read_values(values):
        return

    def fail() -> None:
        bad = ~torch.isfinite(values)
        index = _index(bad)
        raise UsageError(f"{name} must be finite, but {_at(name, index)} is "
                         f"{values[index].item()} ({int(bad.sum())} non-finite values)")

    _require(torch.isfinite(values).all(), fail)


def check_steps(name: str, steps: Tensor, what: str = "") -> None:
    """``steps`` ``[B, S, D]`` are the ego's displacements between consecutive frames (metres in
    ``D`` = 2 or 3 axes): each must be finite and at most :data:`MAX_STEP_METRES` long. ``what``
    says what the step of ``name[b, s]`` is when that entry is not itself a step (a pose). One
    read-back when all is well."""
    if not can_read_values(steps):
        return
    length = steps.double().norm(dim=-1)  # double: a float32 step of 3e38 m has a length

    def fail() -> None:
        check_finite(name, steps)
        index = _index(length > MAX_STEP_METRES)
        raise UsageError(f"{_at(name, index)} moves the ego {length[index].item():.3g} m in one frame{what}; "
                         f"{_STEP_LIMIT}")

    _require((length <= MAX_STEP_METRES).all(), fail)  # False for NaN too


def steps_into(positions: Tensor, start: Tensor | None = None) -> Tensor:
    """The step ``[B, S, D]`` into each of the positions ``[B, S, D]`` from the one before it; into
    the first from ``start`` ``[B, 1, D]`` (default: the origin, the present ego)."""
    first = torch.zeros_like(positions[:, :1]) if start is None else start
    return positions - torch.cat([first, positions[:, :-1]], dim=1)


def check_future_actions(future_actions: Any, batch: int) -> None:
    """``future_actions`` must be finite displacements ``[B, S, 2]`` or poses ``[B, S, 3]``,
    S >= 1, each step at most :data:`MAX_STEP_METRES` long."""
    check_tensor("future_actions", future_actions)
    shape = list(future_actions.shape)
    if future_actions.dim() != 3 or shape[-1] not in (2, 3) or shape[1] < 1 or shape[0] != batch:
        raise UsageError(f"future_actions must be displacements [B, S, 2] or poses [B, S, 3] with B = {batch} "
                         f"and S >= 1, got shape {shape}")
    check_finite("future_actions", future_actions)
    if shape[-1] == 3:
        check_steps("future_actions", steps_into(future_actions[..., :2].double()), " (from the pose before it)")
    else:
        check_steps("future_actions", future_actions)


def check_command(command: Tensor | None, batch: int, reads_command: bool) -> None:
    """``command`` must be None or route commands int64 ``[B]`` in ``0..2``
    (:mod:`t3fast.data.route`), given to a model whose planner reads them."""
    if command is None:
        return
    if not reads_command:
        raise UsageError("this model's planner does not read a route command (world_config.planner = 'phi_act'); "
                         "pass command=None")
    if not isinstance(command, Tensor) or command.dtype not in (torch.int64, torch.int32) or list(
            command.shape) != [batch]:
        got = f"{command.dtype} {list(command.shape)}" if isinstance(command, Tensor) else type(command).__name__
        raise UsageError(f"command must be route commands int64 [B] with B = {batch}, got {got}")

    def fail() -> None:
        bad = command[(command < 0) | (command >= len(COMMANDS))][0]
        raise UsageError(f"command values must be in 0..{len(COMMANDS) - 1} ({', '.join(COMMANDS)}), got {int(bad)}")

    if can_read_values(command):
        _require(((command >= 0) & (command < len(COMMANDS))).all(), fail)


def check_past_occupancy(past_occupancy: Any, grid: tuple[int, int, int]) -> None:
    """``past_occupancy`` must be integer labels ``[B, T, *grid]`` with at least one sample (the
    encoder checks the class ids)."""
    check_tensor("past_occupancy", past_occupancy, floating=False)
    shape = list(past_occupancy.shape)
    if past_occupancy.dim() != 5 or tuple(shape[2:]) != tuple(grid):
        raise UsageError(f"past_occupancy must be labels [B, T, {', '.join(map(str, grid))}], got shape {shape}")
    if past_occupancy.is_floating_point() or past_occupancy.is_complex() or past_occupancy.dtype == torch.bool:
        raise UsageError(f"past_occupancy must be integer class ids (uint8), got {past_occupancy.dtype}")
    if shape[0] == 0:
        raise UsageError("past_occupancy holds no sample (B = 0): forecast at least one")


def check_class_ids(past_occupancy: Tensor, num_classes: int) -> None:
    """Every label of ``past_occupancy`` must be a class id in ``0 .. num_classes - 1`` or the
    ignore id 255."""
    if not can_read_values(past_occupancy):
        return
    bad = ((past_occupancy < 0) | (past_occupancy >= num_classes)) & (past_occupancy != IGNORE)

    def fail() -> None:
        raise UsageError(f"past_occupancy must be class ids in 0..{num_classes - 1} or {IGNORE} (ignore), got "
                         f"{past_occupancy[bad].unique()[:8].tolist()} at {_at('past_occupancy', _index(bad))}")

    _require(~bad.any(), fail)


def check_past_motion(past_motion: Any, batch: int, frames: int) -> None:
    """``past_motion`` must be floating-point ego -> world poses ``[B, T, 4, 4]`` (rigid, within
    :data:`MAX_WORLD_METRES` of the world origin) or displacements ``[B, T - 1, 2]``, the ego
    moving at most :data:`MAX_STEP_METRES` between frames."""
    check_tensor("past_motion", past_motion)
    check_finite("past_motion", past_motion)
    is_poses = past_motion.dim() == 4 and tuple(past_motion.shape[-2:]) == (4, 4)
    expected = [batch, frames, 4, 4] if is_poses else [batch, frames - 1, 2]
    if list(past_motion.shape) != expected:
        raise UsageError(f"past_motion must be poses [B, T, 4, 4] or displacements [B, T - 1, 2] for the "
                         f"{frames} frames of past_occupancy (B = {batch}), got shape {list(past_motion.shape)}")
    if not is_poses:
        check_steps("past_motion", past_motion)
        return
    check_rigid("past_motion", past_motion)
    translations = past_motion[..., :3, 3].double()  # double: differences of world positions
    check_world_positions("past_motion", translations)
    check_steps("past_motion", steps_into(translations, translations[:, :1]), " (from the frame before it)")


def check_rigid(name: str, poses: Tensor) -> None:
    """Each pose ``[..., 4, 4]`` must be a rigid motion: an orthonormal rotation block of
    determinant 1 and the last row 0, 0, 0, 1 (a singular or scaled matrix has no ego frame)."""
    if not can_read_values(poses):
        return
    m = poses.double()
    rotation = m[..., :3, :3]
    eye = torch.eye(3, dtype=m.dtype, device=m.device)
    off = (rotation.transpose(-1, -2) @ rotation - eye).abs().amax((-2, -1))
    off = torch.maximum(off, (torch.linalg.det(rotation) - 1).abs())
    last = device_constant((0.0, 0.0, 0.0, 1.0), m.dtype, m.device)
    off = torch.maximum(off, (m[..., 3, :] - last).abs().amax(-1))

    def fail() -> None:
        index = _index(off > RIGID_TOLERANCE)
        raise UsageError(f"{_at(name, index)} is not a rigid ego -> world pose: its rotation block must be "
                         f"orthonormal with determinant 1 and its last row 0, 0, 0, 1 (within {RIGID_TOLERANCE:g}), "
                         f"off by {off[index].item():.3g}")

    _require((off <= RIGID_TOLERANCE).all(), fail)


def check_world_positions(name: str, translations: Tensor) -> None:
    """Each pose's translation ``[..., 3]`` must place the ego within :data:`MAX_WORLD_METRES` of
    the world origin."""
    if not can_read_values(translations):
        return
    distance = translations.double().norm(dim=-1)

    def fail() -> None:
        index = _index(distance > MAX_WORLD_METRES)
        raise UsageError(f"{_at(name, index)} places the ego {distance[index].item():.3g} m from the world origin; "
                         f"at most {MAX_WORLD_METRES:g} m is accepted (map, UTM and Earth-centred frames stay within)")

    _require((distance <= MAX_WORLD_METRES).all(), fail)


def check_planner_dtype(name: str, motion: Tensor, planner: nn.Module) -> None:
    """The autoregressive planner embeds the past displacements (``motion``, argument ``name``)
    with its own weights, so it plans from motion of their dtype only (the route planner
    converts them)."""
    if not isinstance(planner, MotionPlanner):
        return
    dtype = planner.action_in.weight.dtype
    if motion.dtype != dtype:
        raise UsageError(f"{name} must be {str(dtype).removeprefix('torch.')} like the planner's weights for this "
                         f"model to plan, got {motion.dtype}; convert it, or give future_actions")


def supported_steps(forecaster: nn.Module, planner: nn.Module, past_actions: int, planned: bool) -> int | None:
    """The most future steps a forecast can have (None: no bound): the flow forecaster predicts
    its trained steps in one pass, the route planner plans its trained steps in one pass, and
    the autoregressive planner embeds the time of each of the ``past_actions`` past and planned
    displacements it reads, for as many as it was built for."""
    limits = []
    if isinstance(forecaster, FlowTriplaneForecaster):
        limits.append(forecaster.steps)
    if planned and isinstance(planner, RoutePlanner):
        limits.append(planner.steps)
    elif planned and isinstance(planner, MotionPlanner):  # step k reads past_actions + k displacements
        limits.append(planner.action_time.shape[0] - past_actions + 1)
    return min(limits) if limits else None


def check_horizon(steps: int, limit: int | None, trained: int, name: str) -> None:
    """``steps`` future steps (of argument ``name``) must not exceed the model's ``limit``."""
    if limit is not None and steps > limit:
        raise UsageError(f"{name} asks for {steps} future steps, but this model forecasts at most {limit} "
                         f"(trained on {trained}, world_config.steps)")


def check_plan(forecaster: nn.Module, planner: nn.Module, steps: int, future_actions: Tensor | None,
               command: Tensor | None, past_motion: Tensor) -> None:
    """What a forecast is asked to do: ``steps`` planned from ``past_motion`` (checked) or the
    given ``future_actions``, with ``command``; refused beyond the networks' horizon."""
    batch, frames = past_motion.shape[:2]
    past_actions = frames - 1 if past_motion.dim() == 4 else frames  # poses [B, T, 4, 4] or displacements
    check_command(command, batch, isinstance(planner, RoutePlanner))
    if future_actions is None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise UsageError(f"steps must be a positive integer, got {steps!r}")
        check_planner_dtype("past_motion", past_motion, planner)
        check_horizon(steps, supported_steps(forecaster, planner, past_actions, True), forecaster.steps, "steps")
    else:
        check_future_actions(future_actions, batch)
        limit = supported_steps(forecaster, planner, past_actions, False)
        check_horizon(future_actions.shape[1], limit, forecaster.steps, "future_actions")


def check_devices(device: torch.device, **inputs: Tensor | None) -> None:
    """Every given input on ``device``, where the model's weights are (a mix fails deep inside
    the forecast, naming neither argument); what is not a tensor is left to its own check."""
    for name, value in inputs.items():
        if isinstance(value, Tensor) and value.device != device:
            raise UsageError(f"{name} is on {value.device}, but the model's weights are on {device}: move it there "
                             f"(.to({str(device)!r})) or the model to it")
