"""The whole forecast of one window at batch 1, what ``model.forecast`` does from the past
labels and poses to the future labels and plan: encoding the five past frames, the agents (the
tracker, the box fit), the forecaster, the planner, the render. The shipped weights, a
validation window, the compiled operators versus their pure-PyTorch references (the encoder's
stem, the decoder, the delta fusion and the matching costs); FPS = 1 / time. ``wm-small`` is the
shipped model, ``wm-small-own-frames`` the papers' formulation (the Delta forecaster, every frame
in its own ego frame). Then four windows in one batch against one by one: on the CPU a batch
costs no more than its windows alone."""

from __future__ import annotations

import contextlib

import pytest
import torch
from workloads import reference_ops

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.pretrained import load_world_model


@pytest.mark.parametrize("name", ["wm-small", "wm-small-own-frames"])
@pytest.mark.parametrize("impl", ["fused", "reference"])
def test_whole_forecast(benchmark, impl, name):
    benchmark.group = f"whole forecast ({name}, batch 1, encoding included)"
    model = load_world_model(name)
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    occ, poses = sample.occ[None, : PRESENT + 1], sample.ego_poses[None, : PRESENT + 1]
    with reference_ops(model) if impl == "reference" else contextlib.nullcontext():
        benchmark.pedantic(lambda: model.forecast(occ, poses), rounds=5, warmup_rounds=1)
    benchmark.extra_info["fps"] = 1 / benchmark.stats.stats.median


@pytest.mark.parametrize("how", ["one batch", "window by window"])
def test_four_windows(benchmark, how):
    benchmark.group = "whole forecast (wm-small, 4 windows, encoding included)"
    model = load_world_model("wm-small")
    samples = [SyntheticDriving("val", 2, 20, stride=9)[i] for i in range(4)]
    occ = torch.stack([s.occ[: PRESENT + 1] for s in samples])
    poses = torch.stack([s.ego_poses[: PRESENT + 1] for s in samples])
    if how == "one batch":
        benchmark.pedantic(lambda: model.forecast(occ, poses), rounds=3, warmup_rounds=1)
    else:
        benchmark.pedantic(lambda: [model.forecast(occ[i : i + 1], poses[i : i + 1]) for i in range(4)], rounds=3,
                           warmup_rounds=1)
    benchmark.extra_info["windows_per_s"] = 4 / benchmark.stats.stats.median
