"""The forecast compiled whole (one graph: no host read, no graph break) forecasts what the
eager forecast does, and a batch forecasts each of its windows as it would alone."""

from __future__ import annotations

import pytest
import torch

import t3fast
from t3fast.data.sample import PRESENT, collate_samples
from t3fast.data.synthetic import SyntheticDriving
from t3fast.host_syncs import sync_free
from t3fast.models.world_model import T3Former


@pytest.fixture(scope="module")
def windows():
    data = SyntheticDriving("val", 2, 20, stride=9)
    return collate_samples([data[0], data[3]])


def _same(a, b) -> None:
    assert torch.equal(a.labels, b.labels)
    for field in ("actions", "trajectory", "poses"):
        torch.testing.assert_close(getattr(a, field), getattr(b, field), rtol=0, atol=1e-6)


def test_the_shipped_forecast_traces_into_one_graph_and_forecasts_as_eager(windows):
    """``fullgraph=True``: any host read or untraceable step in the forecast fails the compile."""
    eager = t3fast.load_world_model("wm-small")
    compiled = t3fast.load_world_model("wm-small").compile_forecast(backend="eager")
    occ, motion = windows.past_occ[:1], windows.ego_poses[:1, : PRESENT + 1]
    _same(compiled.forecast(occ, motion), eager.forecast(occ, motion))
    actions = windows.future_actions[:1]
    _same(compiled.forecast(occ, motion, future_actions=actions), eager.forecast(occ, motion, future_actions=actions))


@pytest.mark.parametrize("name", ["wm-small-no-delta", "wm-small-own-frames"])
def test_the_ablations_trace_into_one_graph_too(windows, name):
    """The renders that keep the observed static world (decoding only the voxels that can
    change) and that decode every frame whole; two frames ahead (the trace unrolls the rollout,
    whose later steps repeat the second)."""
    occ, motion = windows.past_occ[:1], windows.ego_poses[:1, : PRESENT + 1]
    compiled = t3fast.load_world_model(name).compile_forecast(backend="eager")
    _same(compiled.forecast(occ, motion, steps=2), t3fast.load_world_model(name).forecast(occ, motion, steps=2))


def test_load_world_model_compiles_on_request(monkeypatch):
    calls = []
    monkeypatch.setattr(T3Former, "compile_forecast", lambda self, **options: calls.append(options) or self)
    assert isinstance(t3fast.load_world_model("wm-small", compile=True), T3Former) and calls == [{}]
    assert isinstance(t3fast.load_world_model("wm-small"), T3Former) and len(calls) == 1


@pytest.mark.parametrize("host_reads", [True, False], ids=["compacted", "sync-free"])
def test_a_batch_forecasts_each_window_as_alone(windows, host_reads):
    """Up to float round-off: the CPU's convolutions sum in another order at another batch size
    (planes within 2e-5), which flips a voxel where two classes' logits tie; a window mixed with
    another's agents or poses would differ in thousands."""
    model = t3fast.load_world_model("wm-small")
    occ, motion = windows.past_occ, windows.ego_poses[:, : PRESENT + 1]
    with sync_free() if not host_reads else torch.no_grad():
        both = model.forecast(occ, motion)
        for n in range(2):
            alone = model.forecast(occ[n : n + 1], motion[n : n + 1])
            assert int((both.labels[n : n + 1] != alone.labels).sum()) <= 20
            torch.testing.assert_close(both.poses[n : n + 1], alone.poses, rtol=0, atol=1e-5)
    assert int((both.labels[0] != both.labels[1]).sum()) > 10_000  # two different windows
