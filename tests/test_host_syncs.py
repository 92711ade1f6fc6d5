"""Host synchronisations: :class:`~t3fast.host_syncs.SyncCounter` finds the ops a GPU run waits
on; the shipped forecast on the CPU waits only where it compacts data-dependent records (the
agents found, the voxels moved, the voxels beyond the grid) and in its input checks, and
without host reads (:func:`~t3fast.host_syncs.sync_free`, as on a GPU) in its input checks alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.device_constants import device_constant
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.pretrained import load_world_model, shipped_names

#: syncing ops of one forecast of the window below at this version; lower it as parts go sync-free
MAX_FORECAST_SYNCS = 58
#: ops dispatched in that forecast (6,564 before the matching costs, the splatting and the box
#: drawing were batched)
MAX_FORECAST_OPS = 4_500
#: ops a GPU-mode forecast dispatches per window more in its batch (1,548 while each window's
#: agents were found, followed, fitted, moved and pasted on their own: 65, the boxes drawn)
MAX_OPS_PER_WINDOW = 80
#: (file, function) prefixes that may still read the device: the agents' variable-length records
#: and the checks of the user's inputs
INPUT_CHECKS = ("models/encoder.py:check_labels", "models/forecast_inputs.py:read_together")
ALLOWED = ("agents/tracker.py:", "forecast/render.py:_fill_unseen", *INPUT_CHECKS)


def test_counts_what_the_host_must_read():
    x = torch.arange(6.0)
    mask = x > 2
    with SyncCounter() as counter:
        x.sum().item()
        mask.nonzero()
        x[mask]
        x[mask] = 0.0
        torch.equal(x, x)
        (x + 1).relu()[torch.tensor([0, 2])]  # an integer index: no wait
        torch.where(mask, x, -x)
    assert dict(counter.by_op) == {"_local_scalar_dense": 1, "nonzero": 1, "index (bool mask)": 2, "equal": 1}
    assert counter.total == 5
    assert counter.dispatched >= 12  # every op, the views and the ones that wait included
    assert set(counter.by_caller) == set()  # none of them ran in t3fast
    assert counter.host_data == {"(outside t3fast)": 2}  # the value 0.0 written and the index [0, 2]


def test_counts_tensors_made_from_host_data_but_not_the_constants_made_once_per_device():
    on_meta = torch.zeros(2, device="meta")
    with SyncCounter() as counter:
        torch.tensor([1.0, 2.0])
        on_meta.new_tensor([1.0, 2.0], device="cpu")
        torch.from_numpy(np.ones(3)).to("meta")  # made from host data, then copied to another device
        torch.ones(3).to("meta")
        torch.zeros(3, device="meta") + on_meta[0]  # no host data
        device_constant((1.0, 2.0), torch.float32, "meta")
        device_constant((1.0, 2.0), torch.float32, "meta")
    assert counter.host_data == {"(outside t3fast)": 5}


@pytest.fixture(scope="module")
def forecast_syncs() -> SyncCounter:
    model = load_world_model("wm-small")
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    with SyncCounter() as counter:
        model.forecast(sample.occ[None, : PRESENT + 1], sample.ego_poses[None, : PRESENT + 1])
    return counter


def test_the_shipped_forecast_waits_only_in_its_agents_records_and_input_checks(forecast_syncs):
    unexpected = {caller: n for caller, n in forecast_syncs.by_caller.items() if not caller.startswith(ALLOWED)}
    assert not unexpected, f"syncing ops outside the agents' records and the input checks: {unexpected}"


def test_the_shipped_forecast_waits_no_more_often_than_before(forecast_syncs):
    assert forecast_syncs.total <= MAX_FORECAST_SYNCS, forecast_syncs.by_caller.most_common(10)


@pytest.mark.parametrize("name", shipped_names())
def test_without_host_reads_the_forecast_waits_only_once_for_its_input_checks(name):
    """As a GPU run: the agents in fixed slots, the voxels to decode gathered into a buffer
    whose length stays on the device, the inputs' values checked together; the same forecast
    as the CPU's compacted records give, for every shipped model."""
    model = load_world_model(name)
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    args = sample.occ[None, : PRESENT + 1], sample.ego_poses[None, : PRESENT + 1]
    with sync_free(), SyncCounter() as counter:
        free = model.forecast(*args)
    assert dict(counter.by_caller) == {"models/forecast_inputs.py:read_together": 1}
    assert not counter.host_data, f"tensors made from host data (a copy that waits on a GPU): {counter.host_data}"
    compacted = model.forecast(*args)
    assert torch.equal(free.labels, compacted.labels) and torch.equal(free.poses, compacted.poses)


def test_on_the_meta_device_the_forecast_reads_nothing_and_copies_nothing_from_the_host():
    """Model and inputs on "meta" (shapes without values) stand in for a GPU: an op that reads a
    value fails there, and a copy of a CPU tensor to the device shows."""
    model = load_world_model("wm-small", device="meta")
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    args = sample.occ[None, : PRESENT + 1].to("meta"), sample.ego_poses[None, : PRESENT + 1].to("meta")
    with SyncCounter() as counter:
        out = model.forecast(*args)
    assert out.labels.device.type == "meta" and out.labels.shape == (1, 6, 200, 200, 16)
    assert counter.total == 0 and not counter.host_data, (counter.by_caller, counter.host_data)


def test_the_shipped_forecast_runs_no_more_ops_than_before(forecast_syncs):
    """Each op is a kernel launch on a GPU (microseconds of the host's time whatever its size)."""
    assert forecast_syncs.dispatched <= MAX_FORECAST_OPS


def test_a_larger_batch_adds_few_ops_as_a_gpu_runs_it():
    """On a GPU the agents of every window are found, followed, fitted and moved in one call
    each (fixed slots): a window more adds the ops that draw it, not a copy of the agents' ~1,400."""
    model = load_world_model("wm-small")
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    dispatched = {}
    for batch in (1, 3):
        occ = sample.occ[None, : PRESENT + 1].expand(batch, -1, -1, -1, -1).contiguous()
        poses = sample.ego_poses[None, : PRESENT + 1].expand(batch, -1, -1, -1).contiguous()
        with sync_free(), SyncCounter() as counter:
            model.forecast(occ, poses)
        dispatched[batch] = counter.dispatched
    assert (dispatched[3] - dispatched[1]) / 2 <= MAX_OPS_PER_WINDOW, dispatched
