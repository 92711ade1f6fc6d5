"""Device mix-ups, caught without a GPU: the code runs with the default device set to "meta",
so a tensor it makes without its inputs' device lands on meta, and the first op that mixes it
with the CPU inputs fails (on a GPU machine that tensor is the CPU one beside CUDA inputs).
The results must equal those of a plain CPU run."""

from __future__ import annotations

import pytest
import torch

from t3fast.commands.demo import save_pictures
from t3fast.data.sample import NUM_FUTURE, PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import UsageError
from t3fast.evaluation.report import evaluate_methods
from t3fast.host_syncs import sync_free
from t3fast.pretrained import load_world_model

SHIPPED = ["wm-small", "wm-small-own-frames", "wm-small-no-delta", "wm-small-single-scale", "wm-small-bev"]


@pytest.fixture(scope="module")
def windows() -> SyntheticDriving:
    return SyntheticDriving("val", 1, 20, stride=9)


def _inputs(windows: SyntheticDriving) -> tuple[torch.Tensor, torch.Tensor]:
    sample = windows[0]
    return sample.occ[None, : PRESENT + 1], sample.ego_poses[None, : PRESENT + 1]


@pytest.mark.parametrize("name", SHIPPED)
def test_the_forecast_makes_every_tensor_on_its_inputs_device(windows, name):
    model = load_world_model(name)
    occ, poses = _inputs(windows)
    expected = model.forecast(occ, poses)
    with torch.device("meta"):
        got = model.forecast(occ, poses)
    assert got.labels.device.type == "cpu"
    assert torch.equal(got.labels, expected.labels) and torch.equal(got.trajectory, expected.trajectory)


def test_the_forecast_as_a_gpu_runs_it_makes_every_tensor_on_its_inputs_device(windows):
    """The fixed-size code a GPU runs (agents in slots, whole-frame moves and decodes,
    :func:`~t3fast.host_syncs.sync_free`), which a CPU run otherwise skips."""
    model = load_world_model("wm-small")
    occ, poses = _inputs(windows)
    expected = model.forecast(occ, poses)
    with sync_free(), torch.device("meta"):
        got = model.forecast(occ, poses)
    assert torch.equal(got.labels, expected.labels) and torch.equal(got.trajectory, expected.trajectory)


def test_a_steered_forecast_and_a_planned_one_with_a_command_stay_on_the_inputs_device(windows):
    model = load_world_model("wm-small")
    occ, poses = _inputs(windows)
    steer = torch.tensor([[[1.0, 0.1]] * NUM_FUTURE])
    command = torch.tensor([windows[0].command])
    with torch.device("meta"):
        steered = model.forecast(occ, poses, future_actions=steer)
        commanded = model.forecast(occ, poses, command=command)
    assert torch.equal(steered.labels, model.forecast(occ, poses, future_actions=steer).labels)
    assert torch.equal(commanded.trajectory, model.forecast(occ, poses, command=command).trajectory)


@pytest.mark.parametrize("argument", ["past_motion", "future_actions", "command"])
def test_an_input_on_another_device_than_the_weights_is_refused_naming_it(windows, argument):
    model = load_world_model("wm-small")
    occ, poses = _inputs(windows)
    given = {"past_motion": poses, "future_actions": torch.zeros(1, NUM_FUTURE, 2), "command": torch.tensor([0])}
    given[argument] = given[argument].to("meta")
    if argument == "future_actions":
        given.pop("command")
    with pytest.raises(UsageError, match=f"^{argument} is on meta, but the model's weights are on cpu"):
        model.forecast(occ, **given)


def test_the_evaluation_its_baselines_and_the_demo_pictures_stay_on_the_inputs_device(windows, tmp_path):
    """What ``t3fast demo`` and ``t3fast eval`` run per window, the steered picture included."""
    model = load_world_model("wm-small")
    loaded = [windows[0]]  # the data as loaded on the CPU (a dataset's own tensors follow the default device)
    expected = evaluate_methods({"t3former": model}, loaded, [0], progress=False)
    with torch.device("meta"):
        got = evaluate_methods({"t3former": model}, loaded, [0], progress=False)
        written = save_pictures(model, loaded, [0], tmp_path)
    assert any("steered" in path.name for path in written)
    for name, row in expected.items():
        assert got[name]["miou"] == row["miou"], name
