"""What the world-model table's rows are: the headline row plans without the route command (it is
derived from the ego's true future), the speed is the whole forecast from past labels and poses,
and a checkpoint saved at its run's step 0 says so in its row."""

from __future__ import annotations

import pytest
import torch

from t3fast.commands.evaluate import load_models
from t3fast.data.sample import PRESENT, collate_samples
from t3fast.data.synthetic import SyntheticDriving
from t3fast.evaluation.report import evaluate_methods, metrics_markdown
from t3fast.evaluation.world_model import measure_speed
from t3fast.forecast import encode as encode_module
from t3fast.pretrained import SHIPPED_DIR, load_world_model


@pytest.fixture(scope="module")
def window():
    return SyntheticDriving("test", 1, stride=29)


def _distance_at_3s(model, batch, command) -> float:
    out = model.forecast(batch.past_occ, batch.ego_poses[:, : PRESENT + 1], command=command)
    truth = batch.future_actions.cumsum(1)
    return float((out.trajectory[0, -1] - truth[0, -1]).norm())


def test_the_headline_row_plans_without_the_route_command(window):
    model = load_world_model("wm-small")
    assert model.reads_command
    results = evaluate_methods({"t3former": model}, window, [0], baselines=False, progress=False)
    assert set(results) == {"t3former", "t3former_gt_ego", "t3former_decoded", "t3former_command"}
    batch = collate_samples([window[0]])
    without, given = _distance_at_3s(model, batch, None), _distance_at_3s(model, batch, batch.command)
    assert without != pytest.approx(given)  # the window tells the two plans apart
    assert results["t3former"]["l2_at"]["3s"] == pytest.approx(without)
    assert results["t3former_decoded"]["l2_at"]["3s"] == pytest.approx(without)
    assert results["t3former_command"]["l2_at"]["3s"] == pytest.approx(given)
    assert results["t3former"]["fps"] > 0 and results["t3former_command"]["fps"] is None


def test_speed_is_timed_on_the_whole_forecast_from_past_labels_and_poses(window, monkeypatch):
    model = load_world_model("wm-small")
    batch = collate_samples([window[0]])
    calls = []
    forecast = model.forecast
    encode = encode_module.encode_sequence

    def counted_forecast(past_occupancy, past_motion, *args, **kwargs):
        calls.append(("forecast", tuple(past_occupancy.shape), tuple(past_motion.shape), args, kwargs))
        return forecast(past_occupancy, past_motion, *args, **kwargs)

    def counted_encode(*args, **kwargs):
        calls.append(("encode",))
        return encode(*args, **kwargs)

    monkeypatch.setattr(model, "forecast", counted_forecast)
    monkeypatch.setattr(encode_module, "encode_sequence", counted_encode)
    speed = measure_speed(model, batch, warmup=1, iters=2)
    grid = tuple(batch.past_occ.shape[2:])
    whole = ("forecast", (1, PRESENT + 1, *grid), (1, PRESENT + 1, 4, 4), (), {})
    assert calls == [whole, ("encode",)] * 3  # every timed step encodes the past frames itself
    assert speed["fps"] > 0 and speed["params"] == sum(p.numel() for p in model.parameters())


def test_a_checkpoint_at_step_0_says_so_in_its_row():
    paths = [SHIPPED_DIR / "wm-small.pt", SHIPPED_DIR / "wm-small-single-scale.pt"]
    models, steps = load_models(paths, torch.device("cpu"))
    assert list(models) == ["t3former", "single_scale"]
    assert steps == {"t3former": torch.load(paths[0], weights_only=True)["step"], "single_scale": 0}
    occ = {"0s": 80.0, "1s": 50.0, "2s": 40.0, "3s": 30.0, "avg": 40.0}
    plan = dict.fromkeys(("1s", "2s", "3s", "avg"))
    record = dict(miou=occ, iou=occ, miou_moving=occ, l2_at=plan, l2_mean=plan, collision=plan, fps=1.0,
                  peak_memory_mb=1.0, params=1)
    text = metrics_markdown({"t3former": record | {"checkpoint_step": 15000},
                             "single_scale": record | {"checkpoint_step": 0}, "copy_paste": record})
    rows = [line.split("|")[1].strip() for line in text.splitlines() if line.startswith("| ")]
    assert rows.count("single_scale (step 0: untrained, its run never beat its start)") == 2
    assert rows.count("t3former") == 2 and rows.count("copy_paste") == 2
