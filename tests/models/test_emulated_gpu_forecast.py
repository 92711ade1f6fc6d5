"""The shipped forecasts as a GPU runs them, on the CPU: the GPU's Python paths (fixed agent
slots, no host reads: :func:`~t3fast.host_syncs.sync_free`) and every operator through the CUDA
glue and kernels, emulated (``tests/cuda_emulation``). They give the CPU's forecasts: what the
demo on a GPU must show (its metrics equal to the CPU run's), for every world model it shows."""

from __future__ import annotations

import pytest
import torch

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.host_syncs import sync_free
from t3fast.pretrained import load_world_model, shipped_names
from tests.cuda_emulation import emulated_ops, requires_emulator

pytestmark = requires_emulator


def _forecasts_as_the_cpu(name: str, windows: int, steps: int = 6) -> torch.Tensor:
    """``windows`` validation windows in one batch, forecast ``steps`` frames ahead through the
    emulated CUDA kernels, against each window forecast alone on the CPU; the emulated
    forecast's labels."""
    model = load_world_model(name)
    data = SyntheticDriving("val", 1, 20, stride=9)
    samples = [data[i] for i in range(windows)]
    occ = torch.stack([s.occ[: PRESENT + 1] for s in samples])
    poses = torch.stack([s.ego_poses[: PRESENT + 1] for s in samples])
    with emulated_ops(), sync_free():
        gpu = model.forecast(occ, poses, steps=steps)
    for i in range(windows):
        cpu = model.forecast(occ[i : i + 1], poses[i : i + 1], steps=steps)
        # the decoders' float32 sums run in another order on the CPU's SIMD units: a label may
        # flip where two classes tie to the last bits (none did where this was written)
        assert gpu.labels[i : i + 1].shape == cpu.labels.shape
        assert (gpu.labels[i : i + 1] != cpu.labels).float().mean().item() < 1e-4
        torch.testing.assert_close(gpu.poses[i : i + 1], cpu.poses, rtol=0, atol=1e-6)
    return gpu.labels


def test_the_shipped_forecast_through_the_cuda_kernels_is_the_cpus():
    """Two windows in one batch: their agents in one set of fixed slots, as a GPU batches them."""
    labels = _forecasts_as_the_cpu("wm-small", windows=2)
    assert not torch.equal(labels[0], labels[1])


@pytest.mark.parametrize("name", [name for name in shipped_names() if name != "wm-small"])
def test_the_ablations_through_the_cuda_kernels_are_the_cpus(name):
    """One window each (the demo's other rows), two frames ahead: those without the Delta or in
    their own frames decode every voxel of every future frame, about 7 s of emulated decoding a
    frame here; the later steps of the rollout run the same code as the second."""
    _forecasts_as_the_cpu(name, windows=1, steps=2)
