"""Where a training step's time goes: ``torch.profiler`` over a few steps of a run
(``train.profile_steps``), summarised in ``out_dir/profile.json``.

The trainer marks each step's phases (``data``: the next batch and its copy to the device;
``forward``: the task's loss; ``backward``; ``optimizer``: the logged values read, clipping and
the optimiser step; with ``train.cuda_graph``, ``step``: all but the data, replayed from a
graph). The summary gives per step the wall time, each phase's host time and, on a
GPU, the device time of the kernels it launched, the kernels launched and the GPU's busy time,
and the ops (CUDA kernels on a GPU) that took most of it::

    t3fast train-wm --config paper train.profile_steps=3
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from pathlib import Path

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile, record_function

PHASES = ("data", "forward", "backward", "optimizer", "step")
SKIP = 2  # steps run before profiling starts: allocator, cuDNN and autotuning warm-up
TOP = 30  # ops (kernels on a GPU) listed in a summary


class StepProfile:
    """Profiles ``steps`` training steps after ``skip``; :meth:`phase` marks a phase of the
    current step, :meth:`step_done` ends it. Writes ``path`` once the profiled steps are done."""

    def __init__(self, path: Path, steps: int, device: torch.device, skip: int = SKIP) -> None:
        self.path, self.steps, self.device, self.skip = path, steps, device, skip
        self._seen = 0
        self._profile: profile | None = None
        self._start = 0.0

    @property
    def active(self) -> bool:
        return self._profile is not None

    @contextlib.contextmanager
    def phase(self, name: str) -> Iterator[None]:
        """Mark ``name`` (one of :data:`PHASES`) while profiling; otherwise nothing."""
        if self._profile is None:
            yield
            return
        with record_function(f"step/{name}"):
            yield

    def step_begin(self) -> None:
        """Start profiling before the first profiled step."""
        if self._seen == self.skip and self._profile is None and self.steps:
            activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if self.device.type == "cuda" else [])
            self._sync()
            self._profile = profile(activities=activities)
            self._profile.__enter__()
            self._start = time.perf_counter()

    def step_done(self) -> None:
        """End a step; after the last profiled one, stop and write the summary."""
        self._seen += 1
        if self._profile is not None and self._seen == self.skip + self.steps:
            self._sync()
            wall = time.perf_counter() - self._start
            self._profile.__exit__(None, None, None)
            self.path.write_text(json.dumps(summarise(self._profile, self.steps, wall, self.device), indent=1) + "\n")
            self._profile = None

    def close(self) -> None:
        """Stop a profile the run ended in (interrupted or failed): nothing is written."""
        if self._profile is not None:
            self._profile.__exit__(None, None, None)
            self._profile = None

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)


def op_times(prof: profile, device: torch.device) -> list[tuple[str, int, float]]:
    """``(name, calls, milliseconds)`` of a finished profile, longest first: on a GPU its CUDA
    kernels and their device time, on a CPU its ops and their self time (the phase marks left
    out)."""
    if device.type == "cuda":
        kernels: dict[str, list[float]] = {}
        for event in prof.events():
            if event.device_type == DeviceType.CUDA:
                kernels.setdefault(event.name, []).append(event.time_range.elapsed_us() / 1e3)
        times = [(name, len(t), sum(t)) for name, t in kernels.items()]
    else:
        times = [(e.key, e.count, e.self_cpu_time_total / 1e3) for e in prof.key_averages()
                 if not e.key.startswith("step/")]
    return sorted(times, key=lambda t: -t[2])


def summarise(prof: profile, steps: int, wall: float, device: torch.device) -> dict:
    """Per-step figures of a finished profile of ``steps`` steps that took ``wall`` seconds."""
    out: dict = {"steps": steps, "device": str(device), "wall_ms_per_step": wall * 1e3 / steps, "phases": {}}
    for event in prof.key_averages():
        if event.key.startswith("step/"):
            out["phases"][event.key[5:]] = {"host_ms_per_step": event.cpu_time_total / 1e3 / steps,
                                           "device_ms_per_step": event.device_time_total / 1e3 / steps}
    times = op_times(prof, device)
    calls = sum(n for _, n, _ in times) / steps
    if device.type == "cuda":
        out["kernels_per_step"] = calls
        out["gpu_busy_ms_per_step"] = sum(ms for _, _, ms in times) / steps
    else:
        out["ops_per_step"] = calls
    out["top"] = [{"name": name[:160], "calls_per_step": n / steps, "ms_per_step": round(ms / steps, 4)}
                  for name, n, ms in times[:TOP]]
    return out
