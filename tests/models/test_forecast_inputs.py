"""``T3Former.forecast`` refuses what it cannot forecast, up front, with one line naming the
argument, the first offending index and what is accepted (a ``UsageError``, a ``ValueError``)."""

from __future__ import annotations

import math
import re

import pytest
import torch

import t3fast
from t3fast.errors import UsageError
from t3fast.models.forecast_inputs import MAX_STEP_METRES

from .test_world_model import _past, aligned

#: what the forecast encodes the past frames with: patched to fail where nothing may be encoded yet
ENCODE = "t3fast.forecast.encode.encode_sequence"


@pytest.fixture(scope="module")
def model():
    return aligned().eval()


def still_poses(b: int = 1) -> torch.Tensor:
    return torch.eye(4).repeat(b, 5, 1, 1)


def walking(b: int = 1) -> torch.Tensor:
    return torch.full((b, 4, 2), 0.5)


def refused(model, message: str, past=None, motion=None, **kwargs) -> str:
    """The one-line message ``model.forecast`` refuses these inputs with, before encoding them."""
    with pytest.raises(UsageError, match=message) as caught:
        model.forecast(_past() if past is None else past, walking() if motion is None else motion, **kwargs)
    assert "\n" not in str(caught.value)
    return str(caught.value)


@pytest.fixture
def no_encoding(model, monkeypatch):
    """Fails a test whose forecast gets as far as encoding the past frames."""

    def encode(*args, **kwargs):
        raise AssertionError("the inputs were encoded before they were checked")

    monkeypatch.setattr(ENCODE, encode)
    return model


def test_an_empty_batch_is_refused(no_encoding):
    refused(no_encoding, r"past_occupancy holds no sample \(B = 0\)", _past()[:0], walking()[:0])
    refused(no_encoding, r"past_occupancy holds no sample \(B = 0\)", _past()[:0], still_poses()[:0])


def test_past_occupancy_must_be_labels_of_the_models_grid(no_encoding):
    refused(no_encoding, r"^past_occupancy must be labels \[B, T, 16, 12, 4\], got shape \[1, 5, 16, 12, 5\]$",
            torch.zeros(1, 5, 16, 12, 5, dtype=torch.uint8))
    refused(no_encoding, r"^past_occupancy must be labels \[B, T, 16, 12, 4\], got shape \[5, 16, 12, 4\]$",
            _past()[0])
    for dtype in (torch.float32, torch.bool):
        refused(no_encoding, f"^past_occupancy must be integer class ids \\(uint8\\), got {dtype}$",
                _past().to(dtype))


@pytest.mark.parametrize("argument", ["past_occupancy", "past_motion", "future_actions"])
def test_arguments_must_be_tensors(no_encoding, argument):
    inputs = {"past": _past(), "motion": walking(), "future_actions": torch.zeros(1, 3, 2)}
    key = {"past_occupancy": "past", "past_motion": "motion"}.get(argument, argument)
    inputs[key] = inputs[key].tolist()
    refused(no_encoding, f"^{argument} must be a torch.Tensor, got list$", **inputs)


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool])
def test_future_actions_must_be_floating_point(no_encoding, dtype):
    future = torch.ones(1, 3, 2, dtype=dtype)
    refused(no_encoding, f"^future_actions must be a floating-point tensor \\(metres\\), got {dtype}$",
            future_actions=future)


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool])
def test_past_motion_must_be_floating_point(no_encoding, dtype):
    for motion in (still_poses().to(dtype), walking().to(dtype)):
        refused(no_encoding, f"^past_motion must be a floating-point tensor \\(metres\\), got {dtype}$", motion=motion)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_the_autoregressive_planner_plans_from_motion_of_its_dtype(model, monkeypatch, dtype):
    steered = model.forecast(_past(), still_poses().to(dtype), future_actions=torch.zeros(1, 2, 2))
    assert steered.labels.shape == (1, 2, 16, 12, 4)  # no plan: any floating-point motion
    monkeypatch.setattr(ENCODE, lambda *a: pytest.fail("encoded before checking the dtype"))
    for motion in (still_poses().to(dtype), walking().to(dtype)):
        message = refused(model, "^past_motion must be", motion=motion)
        assert message == (f"past_motion must be float32 like the planner's weights for this model to plan, "
                           f"got {dtype}; convert it, or give future_actions")


def spoiled_pose(frame: int, spoil) -> torch.Tensor:
    poses = still_poses()
    spoil(poses[0, frame])
    return poses


@pytest.mark.parametrize(
    "spoil",
    [
        lambda m: m.zero_(),  # singular
        lambda m: m[:3, :3].zero_(),  # no rotation at all
        lambda m: m[:3, :3].mul_(2),  # scaled
        lambda m: m[:3, :3].copy_(torch.tensor([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])),  # sheared
        lambda m: m[1, 1].fill_(-1),  # a mirror image: determinant -1
        lambda m: m[3, 3].fill_(0),  # not homogeneous
    ],
)
@pytest.mark.parametrize("frame", [1, 4])
def test_poses_must_be_rigid(no_encoding, spoil, frame):
    refused(no_encoding, rf"^past_motion\[0, {frame}\] is not a rigid ego -> world pose: its rotation block must be "
            r"orthonormal with determinant 1 and its last row 0, 0, 0, 1 \(within 0.001\), off by ",
            motion=spoiled_pose(frame, spoil))


def test_rotated_poses_with_float32_round_off_are_rigid(model):
    yaw = torch.tensor([0.3, 0.25, 0.2, 0.1, 0.0])
    poses = still_poses()
    poses[0, :, 0, 0], poses[0, :, 0, 1] = yaw.cos(), -yaw.sin()
    poses[0, :, 1, 0], poses[0, :, 1, 1] = yaw.sin(), yaw.cos()
    poses[0, :, 0, 3] = torch.arange(-4.0, 1.0) * 0.8 + 1234567.0  # far from the world origin, as UTM is
    assert model.forecast(_past(), poses, steps=2).labels.shape == (1, 2, 16, 12, 4)


@pytest.mark.parametrize("size", [1e30, 3e38, 1e3])
def test_past_displacements_are_bounded(no_encoding, size):
    motion, shown = walking(), re.escape(f"{size:.3g}")
    motion[0, 2, 1] = size
    refused(no_encoding, rf"^past_motion\[0, 2\] moves the ego {shown} m in one frame; at most 100 m per frame "
            r"\(720 km/h at 2 Hz\) is accepted$", motion=motion)


def test_past_poses_are_bounded(no_encoding):
    far = still_poses()
    far[0, :, 0, 3] = 1e30  # every frame 1e30 m away: no step between them, but no place on Earth
    refused(no_encoding, r"^past_motion\[0, 0\] places the ego 1e\+30 m from the world origin; at most 1e\+07 m is "
            r"accepted", motion=far)
    jump = still_poses()
    jump[0, 3:, 1, 3] = 150.0  # 150 m between frames 2 and 3
    refused(no_encoding, r"^past_motion\[0, 3\] moves the ego 150 m in one frame \(from the frame before it\); at most "
            r"100 m per frame", motion=jump)


@pytest.mark.parametrize("size", [1e30, 3e38])
def test_future_actions_are_bounded(no_encoding, size):
    future, shown = torch.full((1, 3, 2), 0.5), re.escape(f"{size:.3g}")
    future[0, 1] = size
    refused(no_encoding, r"^future_actions\[0, 1\] moves the ego .* m in one frame; at most 100 m per frame",
            future_actions=future)
    poses = torch.tensor([[[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0 + size, 0.0, 0.0]]])
    refused(no_encoding, rf"^future_actions\[0, 2\] moves the ego {shown} m in one frame \(from the pose before "
            r"it\); at most 100 m", future_actions=poses)


def test_motion_just_within_the_bound_is_forecast(model):
    fast = torch.tensor([[[MAX_STEP_METRES * 0.6, MAX_STEP_METRES * 0.79]] * 4])  # 99.2 m a frame
    assert math.isclose(float(fast[0, 0].norm()), 99.2, rel_tol=1e-4)
    out = model.forecast(_past(), fast, future_actions=fast[:, :2])
    assert torch.equal(out.actions, fast[:, :2]) and torch.isfinite(out.poses).all()


def test_planned_steps_beyond_the_planner_are_refused_up_front(no_encoding):
    # the autoregressive planner embeds the time of past (4) and planned displacements: 4 + 6
    # learned times, so the 8th step would read an 11th
    refused(no_encoding, r"^steps asks for 8 future steps, but this model forecasts at most 7 \(trained on 6, "
            r"world_config.steps\)$", steps=8)


def test_a_command_or_steps_are_checked_before_encoding(no_encoding):
    refused(no_encoding, r"steps must be a positive integer, got 0", steps=0)
    refused(no_encoding, r"this model's planner does not read a route command", command=torch.tensor([1]))


# ------------------------------------------------------------------ the shipped models' horizons
def zeros_past() -> torch.Tensor:
    return torch.zeros(1, 5, 200, 200, 16, dtype=torch.uint8)


def test_shipped_delta_model_refuses_20_planned_steps_up_front(monkeypatch):
    delta = t3fast.load_world_model("wm-small-no-delta")
    monkeypatch.setattr(ENCODE, lambda *a: pytest.fail("encoded before checking steps"))
    with pytest.raises(UsageError, match=r"^steps asks for 20 future steps, but this model forecasts at most 7 "
                                         r"\(trained on 6, world_config.steps\)$"):
        delta.forecast(zeros_past(), torch.zeros(1, 4, 2), steps=20)


def test_shipped_flow_model_refuses_more_steps_than_it_predicts(monkeypatch):
    flow = t3fast.load_world_model("wm-small")
    monkeypatch.setattr(ENCODE, lambda *a: pytest.fail("encoded before checking steps"))
    with pytest.raises(UsageError, match=r"^steps asks for 7 future steps, but this model forecasts at most 6"):
        flow.forecast(zeros_past(), torch.zeros(1, 4, 2), steps=7)
    with pytest.raises(UsageError, match=r"^future_actions asks for 9 future steps, but this model forecasts at "
                                         r"most 6 \(trained on 6, world_config.steps\)$"):
        flow.forecast(zeros_past(), torch.zeros(1, 4, 2), future_actions=torch.zeros(1, 9, 2))


def test_forecast_command_reports_a_window_with_far_poses_in_one_line(tmp_path, capsys):
    import pickle

    from t3fast.commands.main import main
    from t3fast.data.export import export_synthetic

    root = tmp_path / "occ3d"
    info = export_synthetic(root, "val", 1, 11, progress=False)
    with open(info, "rb") as f:
        infos = pickle.load(f)
    for frames in infos["infos"].values():
        for frame in frames:
            frame["ego2global_translation"] = [1e30, 0.0, 0.0]
    with open(info, "wb") as f:
        pickle.dump(infos, f)
    out = tmp_path / "out"
    assert main(["forecast", "--data", str(root), "--info", str(info), "--ckpt", "wm-small", "--out", str(out)]) == 2
    err = capsys.readouterr().err  # the progress bar's line, then the error's
    assert "Traceback" not in err, err
    assert err.splitlines()[-1].startswith("t3fast forecast: past_motion[0, 0] places the ego 1e+30 m from the "
                                           "world origin; at most 1e+07 m is accepted"), err
    assert not list(out.rglob("*.npz"))


def test_class_ids_are_checked_before_encoding(no_encoding):
    past = _past()
    past[0, 2, 3, 4, 1] = 40
    refused(no_encoding, r"^past_occupancy must be class ids in 0\.\.17 or 255 \(ignore\), got \[40\] at "
            r"past_occupancy\[0, 2, 3, 4, 1\]$", past)


def test_of_the_values_read_together_the_first_check_that_fails_is_reported(no_encoding):
    """One host read for all the values; the refusal is the one an argument-by-argument check
    would give first (the class ids before the motion, the motion before the actions)."""
    past, motion = _past(), walking()
    past[0, 0, 0, 0, 0] = 99
    motion[0, 1, 0] = math.nan
    refused(no_encoding, r"^past_occupancy must be class ids", past, motion)
    refused(no_encoding, r"^past_motion must be finite, but past_motion\[0, 1, 0\] is nan",
            motion=motion, future_actions=torch.full((1, 6, 2), 1e3))
    refused(no_encoding, r"^future_actions\[0, 0\] moves the ego 1\.41e\+03 m",
            future_actions=torch.full((1, 6, 2), 1e3))
