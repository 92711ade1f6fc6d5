"""A whole training step (forward, loss, backward, clipping, optimiser step) captured as one CUDA
graph and replayed (``train.cuda_graph``): one launch a step instead of tens of thousands.

A ``wm-paper`` step launches about 25,500 kernels at any batch size (a 6-step rollout of the
Delta forecaster, the planner's ResNets, their backward and the fused AdamW update): run eagerly,
the GPU waits on the host launching them. Replayed from a graph, the same kernels run back to back.

How a graphed step differs from an eager one:

* Its tensors live in static buffers. Each batch is copied into the captured batch's tensors,
  the replay reruns every kernel on them, and the logged values are the captured outputs,
  overwritten by the next replay (the trainer reads them first).
* One graph per step variant: the task draws the host-side choices of a step before it runs
  (``Task.step_variant``, e.g. where a rollout starts), and the steps that share them, with
  batches of one :func:`layout` (tensor shapes, and any other values), replay one graph. A
  variant runs :data:`WARMUP` eager steps before it is captured (lazy initialisation such as
  cuBLAS workspaces and the optimiser's state must not be captured); they run on the side
  stream the graph is captured on.
* The graphs share one memory pool: nothing a replay leaves in it is read after the next
  replay of any graph (the logged values are read before it, and each replay computes the
  gradients it uses), so variants cost the memory of the largest, not of all together.
* The step must not read the device on the host nor copy host data to it (both break a
  capture): the tasks that offer ``step_variant`` are held to this by tests on the CPU.
* The optimiser is AdamW's fused kernel with its learning rates in device tensors (the
  scheduler writes them in place: a graph reads them at each replay) and a step whose loss or
  gradient norm is not finite changes no weight (the fused kernel's ``found_inf``); the trainer
  then stops the run as it does in eager mode.

On other devices the same step runs without a graph, on the same static buffers and with the
same optimiser, so that the CPU tests exercise everything but the capture itself. A capture that
fails (an op a graph cannot hold) is logged, and that variant runs eagerly from then on.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

log = logging.getLogger(__name__)

WARMUP = 3  # eager steps of a variant before its capture

Body = Callable[[Any], dict[str, Tensor]]


def tensors_of(obj: Any) -> list[Tensor]:
    """The tensors of a batch, in a fixed order: nested in mappings, tuples (named ones too),
    lists and dataclasses; anything else holds none."""
    if isinstance(obj, Tensor):
        return [obj]
    if isinstance(obj, Mapping):
        return [t for v in obj.values() for t in tensors_of(v)]
    if isinstance(obj, list | tuple):
        return [t for v in obj for t in tensors_of(v)]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return [t for f in dataclasses.fields(obj) for t in tensors_of(getattr(obj, f.name))]
    return []


def map_tensors(obj: Any, fn: Callable[[Tensor], Tensor]) -> Any:
    """``obj`` rebuilt with ``fn`` applied to each of its tensors (the nesting of :func:`tensors_of`)."""
    if isinstance(obj, Tensor):
        return fn(obj)
    if isinstance(obj, Mapping):
        return type(obj)({k: map_tensors(v, fn) for k, v in obj.items()})
    if isinstance(obj, tuple) and hasattr(obj, "_fields"):  # namedtuple
        return type(obj)(*(map_tensors(v, fn) for v in obj))
    if isinstance(obj, list | tuple):
        return type(obj)(map_tensors(v, fn) for v in obj)
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.replace(obj, **{f.name: map_tensors(getattr(obj, f.name), fn)
                                           for f in dataclasses.fields(obj) if f.init})
    return obj


def layout(batch: Any) -> tuple:
    """What a graph's static batch must share with a batch copied into it: each tensor's shape,
    dtype and device, and every value that is not a tensor (a graph holds it as it was captured)."""
    if isinstance(batch, Tensor):
        return (tuple(batch.shape), batch.dtype, batch.device)
    if isinstance(batch, Mapping):
        return tuple((k, layout(v)) for k, v in batch.items())
    if isinstance(batch, list | tuple):
        return tuple(layout(v) for v in batch)
    if dataclasses.is_dataclass(batch) and not isinstance(batch, type):
        return tuple(layout(getattr(batch, f.name)) for f in dataclasses.fields(batch))
    try:
        hash(batch)
    except TypeError:  # a value that cannot be compared cheaply: a layout of its own, never captured
        return (type(batch).__name__, id(batch))
    return (type(batch).__name__, batch)


def tensor_learning_rates(optimizer: torch.optim.Optimizer, device: torch.device) -> None:
    """Hold each parameter group's learning rate in a 0-dim float32 tensor on ``device`` (kept
    when it already is one), before a scheduler is built on the optimiser: a captured step
    reads the rate the scheduler writes into it in place."""
    for group in optimizer.param_groups:
        lr = group["lr"]
        if not (isinstance(lr, Tensor) and lr.device == device):
            group["lr"] = torch.tensor(float(lr), dtype=torch.float32, device=device)


_FLAGS = ("fused", "capturable", "foreach")  # how an optimiser computes, not what it holds


def portable_optimizer_state(optimizer: torch.optim.Optimizer) -> dict[str, Any]:
    """``optimizer.state_dict()`` as an eager AdamW holds it (learning rates as floats, step
    counts on the host, neither fused nor capturable), so that a run written by either kind
    resumes with either (a graphed run resumed on several processes runs eagerly)."""
    state = optimizer.state_dict()
    groups = [{**g, **{k: float(g[k]) for k in ("lr", "initial_lr") if k in g},
               "fused": None, "capturable": False, "foreach": None} for g in state["param_groups"]]
    states = {k: {**v, "step": v["step"].detach().to("cpu", torch.float32)} if "step" in v else v
              for k, v in state["state"].items()}
    return {"state": states, "param_groups": groups}


def portable_scheduler_state(scheduler: torch.optim.lr_scheduler.LRScheduler) -> dict[str, Any]:
    """``scheduler.state_dict()`` with the rates it lists as floats."""
    state = scheduler.state_dict()
    return state | {k: [float(v) for v in state[k]] for k in ("base_lrs", "_last_lr") if k in state}


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict[str, Any], device: torch.device) -> None:
    """Load ``state`` (:func:`portable_optimizer_state`) into ``optimizer``, which keeps its own
    way of computing: a fused optimiser gets its step counts on ``device`` and its rates in
    tensors there (:func:`tensor_learning_rates`)."""
    flags = [{k: g[k] for k in _FLAGS if k in g} for g in optimizer.param_groups]
    optimizer.load_state_dict(state)
    for group, kept in zip(optimizer.param_groups, flags, strict=True):
        group.update(kept)
    if any(g.get("fused") for g in optimizer.param_groups):
        for held in optimizer.state.values():
            if "step" in held:
                held["step"] = held["step"].to(device, torch.float32)
        tensor_learning_rates(optimizer, device)


def graph_optimizer(groups: list[dict[str, Any]], lr: float, device: torch.device) -> torch.optim.AdamW:
    """AdamW for a graphed step: the fused kernel (capturable on CUDA), learning rates in tensors on ``device``."""
    optimizer = torch.optim.AdamW(groups, lr=lr, fused=True, capturable=device.type == "cuda")
    tensor_learning_rates(optimizer, device)
    return optimizer


@dataclass
class _Captured:
    """A variant's graph (None off CUDA: the body reruns), its static batch and outputs."""

    graph: torch.cuda.CUDAGraph | None
    batch: Any
    inputs: list[Tensor]
    outputs: dict[str, Tensor]


class GraphedStep:
    """Runs ``body(batch) -> {name: 0-dim tensor}``, a whole training step, from static buffers;
    on CUDA, replays it as one CUDA graph per (variant, batch layout) after :data:`WARMUP` eager
    steps. See the module docstring.

    Attributes: ``captured`` (graphs), ``replays`` and ``eager_steps`` (counts), ``failures``
    (why a capture failed, by variant).
    """

    def __init__(self, body: Body, device: torch.device, warmup: int = WARMUP) -> None:
        self.body, self.device, self.warmup = body, device, warmup
        self._graphs: dict[Hashable, _Captured] = {}
        self._runs: dict[Hashable, int] = {}
        self._failed: set[Hashable] = set()
        self.replays = self.eager_steps = 0
        self.failures: dict[str, str] = {}
        self._stream = torch.cuda.Stream(device) if device.type == "cuda" else None
        self._pool = torch.cuda.graph_pool_handle() if device.type == "cuda" else None

    @property
    def captured(self) -> int:
        return len(self._graphs)

    def report(self) -> dict[str, Any]:
        """Counts for a run's record: graphs captured, replays, eager steps, failed captures."""
        return {"graphs": self.captured, "replays": self.replays, "eager_steps": self.eager_steps,
                "failures": dict(self.failures)}

    def __call__(self, batch: Any, variant: Hashable = None) -> dict[str, Tensor]:
        """One training step on ``batch``; the returned tensors stay valid until the next call."""
        tensors = tensors_of(batch)
        key = (variant, layout(batch))
        captured = self._graphs.get(key)
        if captured is None and key not in self._failed and self._runs.get(key, 0) >= self.warmup:
            captured = self._capture(key, batch)
        if captured is None:
            self._runs[key] = self._runs.get(key, 0) + 1
            self.eager_steps += 1
            return self._eager(batch)
        if tensors:
            torch._foreach_copy_(captured.inputs, tensors)
        self.replays += 1
        if captured.graph is None:
            return self.body(captured.batch)
        captured.graph.replay()
        return captured.outputs

    def _eager(self, batch: Any) -> dict[str, Tensor]:
        if self._stream is None:
            return self.body(batch)
        current = torch.cuda.current_stream(self.device)
        self._stream.wait_stream(current)
        with torch.cuda.stream(self._stream):  # the stream the capture runs on: its lazy set-up done
            out = self.body(batch)
        current.wait_stream(self._stream)
        return out

    def _capture(self, key: Hashable, batch: Any) -> _Captured | None:
        static = map_tensors(batch, torch.clone)
        if self._stream is None:
            captured = _Captured(None, static, tensors_of(static), {})
            self._graphs[key] = captured
            return captured
        graph = torch.cuda.CUDAGraph()
        self._stream.wait_stream(torch.cuda.current_stream(self.device))
        try:
            # thread_local: the process group's watchdog thread may query events meanwhile
            with torch.cuda.graph(graph, pool=self._pool, stream=self._stream, capture_error_mode="thread_local"):
                outputs = self.body(static)
        except RuntimeError as exc:
            reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            self._failed.add(key)
            self.failures[repr(key[0])] = reason
            log.warning("train.cuda_graph: the step (variant %r) could not be captured, it runs eagerly: %s",
                        key[0], reason)
            return None
        captured = _Captured(graph, static, tensors_of(static), outputs)
        self._graphs[key] = captured
        return captured
