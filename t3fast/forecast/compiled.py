"""The forecast compiled whole (after its input checks): the stages of
:mod:`t3fast.forecast.pipeline` traced into one graph by ``torch.compile``, on CUDA replayed as
one CUDA graph. It runs as on a GPU on any device (:func:`~t3fast.host_syncs.sync_free`): the
agents in fixed slots, nothing read on the host, so nothing breaks the graph; the forecast is
the eager one."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from t3fast.forecast.pipeline import ForecastPipeline
from t3fast.forecast.records import Forecast
from t3fast.host_syncs import sync_free


def compiled_forecast(pipeline: ForecastPipeline, device: torch.device, **options: Any) -> Callable[..., Forecast]:
    """``pipeline`` (called as it is, with checked arguments) compiled by
    ``torch.compile(fullgraph=True, **options)``; by default ``mode="reduce-overhead"`` on CUDA
    (Inductor's kernels, replayed as CUDA graphs: one launch for the whole forecast) and
    Inductor's default elsewhere; ``backend="cudagraphs"`` replays the eager kernels as CUDA
    graphs without generating any (it compiles in seconds instead of minutes). The first call
    with each input shape compiles; a forecast a CUDA graph returns is copied out of the graph's
    buffers, which the next replay overwrites."""
    options.setdefault("fullgraph", True)
    if device.type == "cuda" and "backend" not in options and "mode" not in options:
        options["mode"] = "reduce-overhead"
    graphs = device.type == "cuda" and (options.get("mode") == "reduce-overhead"
                                        or options.get("backend") == "cudagraphs")
    compiled = torch.compile(pipeline.__call__, **options)

    def run(*args: Any) -> Forecast:
        if graphs:
            torch.compiler.cudagraph_mark_step_begin()
        with sync_free():
            out = compiled(*args)
        if not graphs:
            return out
        return Forecast(out.labels.clone(), [t.map(torch.clone) for t in out.triplanes], out.actions.clone(),
                        out.trajectory.clone(), out.poses.clone())

    return run
