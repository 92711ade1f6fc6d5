"""The whole forecast, ``model.forecast(past labels, past poses)``: encoding the 5 past frames,
the agents (tracker, box fit), the forecaster, the planner and the 6 future frames rendered to
labels, of a synthetic validation window (repeated ``--batch`` times). Sizes: ``shipped`` (the
shipped ``wm-small`` weights) and the untrained presets (``small``, ``paper``: their speed does
not depend on the weights; ``tiny`` for dry runs). One JSON line per (size, mode, batch) is
appended to ``--out`` as soon as it is measured.

Modes:
  eager            the compiled t3fast operators, plain PyTorch around them
  eager-reference  the pure-PyTorch references of the decoder and delta fusion instead
  cuda-graph       ``eager`` captured once in a CUDA graph and replayed (CUDA only)
  compile          ``model.compile_forecast()`` (what ``load_world_model(..., compile=True)``
                   does): the forecast after its input checks traced whole, Inductor plus one
                   CUDA graph on a GPU (``mode="default"`` on the CPU)
  compile-graphs   ``model.compile_forecast(backend="cudagraphs")``: traced whole, the eager
                   kernels replayed as CUDA graphs (no code generated: compiles in seconds)

Each row: median and 90th-percentile time of one call, FPS (windows forecast per second:
batch / median), in eager modes the host synchronisations of one call
(:class:`~t3fast.host_syncs.SyncCounter`), and the peak memory of the mode
(``torch.cuda.max_memory_allocated`` / ``max_memory_reserved`` since
the model was built: weights, inputs, activations and graph pools). With ``--profile DIR``,
one more call runs under ``torch.profiler``: ``DIR/<size>-<mode>-b<batch>.json`` holds its
kernels launched, the GPU's busy time and the kernels that took it (on a CPU, the ops), so a
row says where its time goes.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import statistics
import sys
import time
import traceback
from dataclasses import replace
from pathlib import Path

import torch

from benchmarks.workloads import reference_ops

MODES = ["eager", "eager-reference", "cuda-graph", "compile", "compile-graphs"]


def sizes() -> dict:
    """Named (autoencoder, world model) configs of the untrained sizes: the presets, and ``tiny``
    (``small`` on a 32 x 32 x 8 grid) for dry runs."""
    from t3fast.presets import WORLD_MODEL_SIZES, autoencoder_size, world_model_size

    out = {name: (autoencoder_size(name), world_model_size(name)) for name in WORLD_MODEL_SIZES}
    out["tiny"] = (replace(autoencoder_size("small"), grid=(32, 32, 8)), world_model_size("small"))
    return out


def build(size: str, device: torch.device, batch: int):
    """The world model of a named size (``shipped``: the shipped weights) and the past labels
    ``[batch, 5, X, Y, Z]`` and poses ``[batch, 5, 4, 4]`` of a validation window."""
    from t3fast.data.sample import PRESENT
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.models.world_model import T3Former
    from t3fast.pretrained import load_world_model

    torch.manual_seed(0)
    if size == "shipped":
        model = load_world_model("wm-small")
    else:
        ae, world = sizes()[size]
        model = T3Former.from_config(ae, world)
    model = model.to(device).eval()
    x, y, z = model.encoder.config.grid
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    occupancy = sample.occ[None, : PRESENT + 1, :x, :y, :z].expand(batch, -1, -1, -1, -1).contiguous()
    poses = sample.ego_poses[None, : PRESENT + 1].expand(batch, -1, -1, -1).contiguous()
    return model, occupancy.to(device), poses.to(device)


def step_function(model, occupancy, poses, mode: str, device: torch.device):
    """A no-argument callable running one whole forecast, and a context to run it in."""

    def step():
        out = model.forecast(occupancy, poses)
        return out.labels, out.actions

    if mode in ("eager", "eager-reference"):
        return step, reference_ops(model) if mode == "eager-reference" else contextlib.nullcontext()
    if mode == "compile":
        model.compile_forecast()
        return step, contextlib.nullcontext()
    if mode == "compile-graphs":
        model.compile_forecast(backend="cudagraphs")
        return step, contextlib.nullcontext()
    if mode == "cuda-graph":
        if device.type != "cuda":
            raise RuntimeError("cuda-graph needs a GPU")
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):  # warm-up off the default stream, as capture requires
            for _ in range(3):
                step()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            step()
        return graph.replay, contextlib.nullcontext()
    raise ValueError(f"unknown mode {mode!r}")


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(fn, device: torch.device, warmup: int, min_iters: int, max_iters: int, seconds: float) -> list[float]:
    """Step times (s): ``warmup`` untimed calls, then calls until ``seconds`` have passed and at
    least ``min_iters`` (at most ``max_iters``) were timed, each ended by a synchronisation."""
    for _ in range(warmup):
        fn()
    sync(device)
    times: list[float] = []
    while len(times) < max_iters and (len(times) < min_iters or sum(times) < seconds):
        start = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return times


def profile_call(fn, device: torch.device) -> dict:
    """One call of ``fn`` under ``torch.profiler``: its wall time; on a GPU the kernels it ran
    (count, summed busy time, the ``TOP`` that took longest, by name), on a CPU its ops (by self
    time), as :func:`~t3fast.training.step_profile.op_times` lists them."""
    from torch.profiler import ProfilerActivity, profile

    from t3fast.training.step_profile import TOP, op_times

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    sync(device)
    with profile(activities=activities) as prof:
        start = time.perf_counter()
        fn()
        sync(device)
        wall = time.perf_counter() - start
    out: dict = {"wall_ms": wall * 1e3}
    times = op_times(prof, device)
    if device.type == "cuda":
        out["kernels"] = sum(n for _, n, _ in times)
        out["gpu_busy_ms"] = sum(ms for _, _, ms in times)
    else:
        out["ops"] = sum(n for _, n, _ in times)
    out["top"] = [{"name": name[:160], "count": n, "ms": round(ms, 4)} for name, n, ms in times[:TOP]]
    return out


def run_row(size: str, mode: str, device: torch.device, quick: bool, batch: int = 1,
            profile_dir: Path | None = None) -> dict:
    row: dict = {"size": size, "mode": mode, "device": str(device), "batch": batch}
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
    model, occupancy, poses = build(size, device, batch)
    row["params_m"] = sum(p.numel() for p in model.parameters()) / 1e6
    row["weights_mb"] = sum(p.numel() * p.element_size() for p in model.parameters()) / 2**20
    start = time.perf_counter()
    fn, context = step_function(model, occupancy, poses, mode, device)
    with context, torch.no_grad():
        warmup = 1 if quick else (3 if mode.startswith("compile") else 2)
        times = measure(fn, device, warmup, min_iters=2 if quick else 10, max_iters=2 if quick else 200,
                        seconds=0.0 if quick else 2.0)
        counting = time.perf_counter()
        if mode.startswith("eager"):  # what a call waits on (t3fast.host_syncs), counted in one more call
            from t3fast.host_syncs import SyncCounter

            with SyncCounter() as counter:
                fn()
            row["host_syncs"] = counter.total
            row["host_data"] = sum(counter.host_data.values())
        if profile_dir is not None:
            profiled = profile_call(fn, device)
            profile_dir.mkdir(parents=True, exist_ok=True)
            (profile_dir / f"{size}-{mode}-b{batch}.json").write_text(json.dumps(profiled, indent=1) + "\n")
            row.update({k: profiled[k] for k in ("kernels", "gpu_busy_ms") if k in profiled})
        counting = time.perf_counter() - counting
    row["setup_s"] = time.perf_counter() - start - sum(times) - counting  # capture / compilation and warm-up
    row["iters"] = len(times)
    row["median_ms"] = statistics.median(times) * 1e3
    row["p90_ms"] = sorted(times)[math.ceil(0.9 * len(times)) - 1] * 1e3  # nearest rank
    row["fps"] = batch * 1e3 / row["median_ms"]
    if device.type == "cuda":
        row["peak_allocated_mb"] = (torch.cuda.max_memory_allocated(device) - base) / 2**20
        row["peak_reserved_mb"] = torch.cuda.max_memory_reserved(device) / 2**20
    del fn, model, occupancy, poses
    if mode.startswith("compile"):
        torch._dynamo.reset()  # drop the compiled code and what its guards hold
    gc.collect()
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.gpu.forecast", description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    parser.add_argument("--sizes", default="shipped,small,paper", help="comma-separated world model sizes")
    parser.add_argument("--batch", type=int, default=1, help="windows per call")
    parser.add_argument("--modes", default=",".join(MODES), help=f"comma-separated, from {MODES}")
    parser.add_argument("--quick", action="store_true", help="two timed steps per row")
    parser.add_argument("--out", type=Path, required=True, help="JSON lines file (appended to)")
    parser.add_argument("--profile", type=Path, help="folder for one profiled call per row")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    sizes, modes = args.sizes.split(","), args.modes.split(",")
    unknown = [m for m in modes if m not in MODES]
    if unknown:
        parser.error(f"unknown modes {unknown}; expected some of {MODES}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    failures = 0
    for mode in modes:  # every size of a mode before the next (slower to set up) mode
        for size in sizes:
            try:
                row = run_row(size, mode, device, args.quick, args.batch, args.profile)
                print(f"{size:>7} {mode:<16} x{args.batch:<3} {row['median_ms']:9.2f} ms {row['fps']:8.1f} FPS"
                      + (f" {row['peak_allocated_mb']:8.0f} MB" if "peak_allocated_mb" in row else ""), flush=True)
            except Exception as exc:
                traceback.print_exc()
                failures += 1
                row = {"size": size, "mode": mode, "device": str(device), "batch": args.batch,
                       "error": f"{type(exc).__name__}: {exc}"}
                torch._dynamo.reset()
                gc.collect()
            with args.out.open("a") as f:
                f.write(json.dumps(row) + "\n")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
