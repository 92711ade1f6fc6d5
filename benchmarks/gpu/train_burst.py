"""A timed burst of ``t3fast train-ae`` / ``train-wm`` steps, one process per device under
torchrun::

    python -m torch.distributed.run --standalone --nproc_per_node=1 benchmarks/gpu/train_burst.py \\
        --backend nccl --seconds 40 --result OUT/result.json -- train-ae --config paper train.steps=100000 ...

Each process joins the process group itself (NCCL on GPUs, gloo on CPUs) before the command
runs, so even a single-GPU run sends the trainer's collectives (metric averages, stop votes,
checkpoint gathers) through NCCL; with more than one process the trainer also wraps the model
in DistributedDataParallel. Once training has run ``--seconds`` and at least ``--min-steps``
steps, the process sends itself SIGINT: the trainer's Ctrl-C path stops every rank after the
same step and writes ``last.pt``. Rank 0 writes ``--result``: throughput from the trainer's
``metrics.jsonl`` (``samples_per_s`` of every logged window but the first, which holds the
warm-up), steps, world size, AMP dtype and peak GPU memory.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import sys
import threading
import time
from pathlib import Path

import torch
import torch.distributed as dist


def nccl_version() -> str:
    """``major.minor.patch`` (torch returns a tuple, or an int such as 2708 in old releases)."""
    version = torch.cuda.nccl.version()
    return ".".join(map(str, version)) if isinstance(version, tuple) else str(version)


def _die_with_parent() -> None:
    """Linux: get SIGKILL when the torchrun agent dies, so no worker outlives a killed stage."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _join_group(backend: str) -> torch.device:
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = torch.device("cuda", local_rank) if backend == "nccl" else torch.device("cpu")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if "RANK" in os.environ and not dist.is_initialized():
        dist.init_process_group(backend, device_id=device if device.type == "cuda" else None)
        probe = torch.ones(1, device=device)
        dist.all_reduce(probe)
        if int(probe.item()) != dist.get_world_size():
            raise RuntimeError(f"all_reduce over {backend} gave {probe.item()}, expected {dist.get_world_size()}")
    return device


class _Burst:
    """Wraps ``Trainer.fit``: starts the stop timer, remembers the trainer and the wall time."""

    def __init__(self, seconds: float, min_steps: int):
        self.seconds, self.min_steps = seconds, min_steps
        self.trainer = None
        self.fit_s = 0.0
        self.stopped_by_timer = False

    def install(self) -> None:
        from t3fast.training.trainer import Trainer

        fit, burst = Trainer.fit, self

        def timed_fit(trainer):
            burst.trainer = trainer
            done = threading.Event()
            watcher = threading.Thread(target=burst._watch, args=(trainer, done), daemon=True)
            start = time.perf_counter()
            watcher.start()
            try:
                return fit(trainer)
            finally:
                burst.fit_s = time.perf_counter() - start
                done.set()

        Trainer.fit = timed_fit

    def _watch(self, trainer, done: threading.Event) -> None:
        start = time.perf_counter()
        while not done.wait(0.2):
            if time.perf_counter() - start >= self.seconds and trainer.step >= self.min_steps:
                self.stopped_by_timer = True
                os.kill(os.getpid(), signal.SIGINT)  # the trainer's own Ctrl-C: stop after this step
                return


def _cli(argv: list[str]) -> int:
    from t3fast.commands.main import build_parser, main

    # tracebacks in the log instead of one-line errors, where the CLI has --debug
    has_debug = any("--debug" in action.option_strings for action in build_parser()._actions)
    return main((["--debug"] if has_debug else []) + argv)


def _throughput(metrics: Path) -> dict:
    events = []
    if metrics.is_file():
        for line in metrics.read_text().splitlines():
            if line.strip():
                record = json.loads(line)
                if record.get("event") == "train":
                    events.append(record)
    rates = [e["values"]["samples_per_s"] for e in events]
    steady = rates[1:] or rates
    return {
        "logged_windows": len(rates),
        "samples_per_s": statistics.median(steady) if steady else None,
        "samples_per_s_first_window": rates[0] if rates else None,
        "last_loss": events[-1]["values"].get("loss") if events else None,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.gpu.train_burst", description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=["nccl", "gloo"], required=True)
    parser.add_argument("--seconds", type=float, required=True, help="training time before the stop")
    parser.add_argument("--min-steps", type=int, default=2, help="steps before the stop, whatever the time")
    parser.add_argument("--result", type=Path, required=True, help="JSON written by rank 0")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the t3fast command line")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no t3fast command given")

    _die_with_parent()
    device = _join_group(args.backend)
    world, rank = (dist.get_world_size(), dist.get_rank()) if dist.is_initialized() else (1, 0)
    burst = _Burst(args.seconds, args.min_steps)
    burst.install()
    start = time.perf_counter()
    rc = _cli(command)
    if rc == 130 and burst.stopped_by_timer:  # stopped by the timer, as planned
        rc = 0
    trainer = burst.trainer
    if rank == 0:
        result = {
            "command": command,
            "returncode": rc,
            "backend": args.backend,
            "world_size": world,
            "device": str(device),
            "total_s": time.perf_counter() - start,
            "fit_s": burst.fit_s,
            "stopped_by_timer": burst.stopped_by_timer,
        }
        if args.backend == "nccl":
            try:
                result["nccl"] = nccl_version()
                result["peak_allocated_mb"] = torch.cuda.max_memory_allocated(device) / 2**20
            except Exception as exc:  # the throughput below matters more than these
                result["cuda_info_error"] = f"{type(exc).__name__}: {exc}"
        if trainer is not None:
            amp = getattr(trainer, "amp_dtype", None)
            result.update(
                steps=trainer.step,
                batch_per_process=trainer.cfg.batch_size,
                amp=str(amp).replace("torch.", "") if amp is not None else "off",
                ddp=type(trainer.model).__name__ == "DistributedDataParallel",
                cuda_graph=trainer.graphed.report() if getattr(trainer, "graphed", None) is not None else None,
                out_dir=str(trainer.out_dir),
            )
            result.update(_throughput(Path(trainer.out_dir) / "metrics.jsonl"))
        args.result.parent.mkdir(parents=True, exist_ok=True)
        args.result.write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps(result, indent=2))
    if dist.is_initialized():  # the command's cleanup normally left the group already
        dist.destroy_process_group()
    return rc


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    # past the interpreter's teardown: there a gloo worker thread, still joinable after the burst
    # had finished and written its result, aborted one rank under load ("terminate called
    # without an active exception"), failing a burst that had measured
    os._exit(code)
