"""Stage 2: the loss learns, and train-wm -> eval -> forecast -> demo work end to end."""

from __future__ import annotations

import dataclasses
import itertools
import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from PIL import Image

from t3fast.commands.demo import checkpoint_paths
from t3fast.commands.main import main
from t3fast.data.export import export_synthetic
from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import ConfigError
from t3fast.evaluation.world_model import SharedRollout, evaluate_forecasts, evaluate_many, t3former_method
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.io.checkpoint import load_checkpoint
from t3fast.models.triplane import Triplane
from t3fast.presets import preset
from t3fast.pretrained import export_weights, load_world_model
from t3fast.training.configs import WorldLossConfig
from t3fast.training.gathered import fits_on, nbytes
from t3fast.training.graphed_step import WARMUP
from t3fast.training.trainer import Trainer
from t3fast.training.world_model.forwards import RolloutModel
from t3fast.training.world_model.latent_cache import (
    AlignedBatches,
    AlignedLatentCache,
    LabelledAlignedWindows,
    ResidentAlignedWindows,
    resident_bytes,
)
from t3fast.training.world_model.loss import rollout_loss
from t3fast.training.world_model.motion_loss import motion_loss
from t3fast.training.world_model.task import StepChoices, WorldModelTask
from t3fast.training.world_model.windows import SequenceBatch, ego_aligned_window, rollout_frames
from t3fast.viz.viewer import read_viewer_data

from ..models.test_world_model import tiny_world_model
from .tiny_runs import TINY_AE, TINY_WM


def shifting_sequence(frames: int = 11, grid=(16, 12, 4)) -> torch.Tensor:
    """A box moving one cell along x per frame over a floor: ``[1, frames, X, Y, Z]``."""
    occ = torch.full((frames, *grid), 17, dtype=torch.uint8)
    occ[..., 0] = 11
    for t in range(frames):
        occ[t, t % (grid[0] - 3) : t % (grid[0] - 3) + 3, 4:8, 1:3] = 1
    return occ[None]


def test_tiny_world_model_fits_a_moving_box():
    torch.manual_seed(0)
    model = tiny_world_model(RolloutModel).train()
    occ = shifting_sequence()
    planes = model.encode_sequence(occ)
    past = torch.zeros(1, 4, 2)
    future = torch.tensor([[[1.0, 0.0]] * 6])
    cfg = WorldLossConfig(num_occupied=200, num_near_free=100, num_far_free=50)
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.Adam(params, lr=3e-3)
    first = None
    for _ in range(100):
        loss, parts = rollout_loss(model, planes, occ, past, future, 0, 2, cfg)
        opt.zero_grad()
        loss.backward()
        opt.step()
        first = first or parts
    assert parts["triplane"] < 0.35 * first["triplane"]
    assert parts["occupancy"] < 0.05 * first["occupancy"]
    assert parts["action"] < 0.01 * first["action"]


def test_own_frames_preset_encodes_frames_once(world_ckpt, tmp_path):
    """The papers' formulation reads its frames' triplanes from a cache written once per encoder."""
    args = ["train-wm", "--config", "small-own-frames", "--ae", str(world_ckpt.parent.parent / "ae" / "last.pt"),
            f"data.cache_dir={tmp_path / 'cache'}", *TINY_WM, "train.eval_every=0"]
    for run in ("a", "b"):
        assert main([*args, f"train.out_dir={tmp_path / run}", "train.steps=1"]) == 0
    assert len(list((tmp_path / "cache").glob("triplanes-*/scene*.pt"))) == 1  # one scene, encoded once
    assert not load_world_model(tmp_path / "a" / "last.pt").world_config.ego_aligned


def test_train_log_has_every_loss_part(world_ckpt):
    events = [json.loads(line) for line in (world_ckpt.parent / "metrics.jsonl").read_text().splitlines()]
    train = [e for e in events if e["event"] == "train"]
    assert [e["step"] for e in train] == [1, 2]
    assert {"loss", "latent", "copy_latent", "flow_moving", "flow_static"} <= set(train[-1]["values"])
    assert any(e["event"] == "eval" and "miou_avg" in e["values"] for e in events)


def test_the_route_planner_trains_with_the_forecaster_and_is_scored_with_and_without_the_command(
        world_ckpt, tmp_path, capsys):
    root = world_ckpt.parent.parent
    out = tmp_path / "route"
    args = ["train-wm", "--config", "small", "--ae", str(root / "ae" / "last.pt"), f"data.cache_dir={root / 'cache'}",
            f"train.out_dir={out}", *TINY_WM, "train.eval_every=0", "train.steps=2", "model.planner=route",
            "planner_lr_scale=1.0"]
    assert main(args) == 0
    train = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert {"plan_l2", "plan_l2_3s", "flow_moving"} <= set(train[-1]["values"])
    model = load_world_model(out / "last.pt")
    assert model.reads_command and model.planner.head[-1].weight.abs().sum() > 0  # left constant turn rate
    capsys.readouterr()
    assert main(["eval", str(out / "last.pt"), "--scenes", "1", "--stride", "29", "--out", str(tmp_path / "ev")]) == 0
    metrics = json.loads((tmp_path / "ev" / "metrics.json").read_text())
    assert {"t3former", "t3former_command"} <= set(metrics)
    assert metrics["t3former_command"]["l2_mean"]["avg"] is not None


def test_eval_writes_the_metrics_schema(world_ckpt, tmp_path, capsys):
    assert main(["eval", str(world_ckpt), "--scenes", "1", "--stride", "29", "--out", str(tmp_path)]) == 0
    assert "| t3former |" in capsys.readouterr().out
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert set(metrics) == {"t3former", "t3former_gt_ego", "t3former_decoded", "t3former_command", "copy_paste",
                            "constant_velocity", "constant_turn_rate", "warp_const_vel", "warp_gt_ego",
                            "track_const_vel", "track_gt_ego"}
    assert metrics["t3former_gt_ego"]["l2_at"]["3s"] is None  # steered: plans nothing
    keys = {"miou", "miou_moving", "iou", "l2_at", "l2_mean", "collision", "fps", "peak_memory_mb", "params",
            "checkpoint_step"}
    assert all(set(m) == keys for m in metrics.values())
    model = metrics["t3former"]
    assert set(model["miou"]) == {"0s", "1s", "2s", "3s", "avg"} and set(model["l2_at"]) == {"1s", "2s", "3s", "avg"}
    assert all(0 <= v <= 100 for v in model["miou"].values()) and model["fps"] > 0 and model["params"] > 0
    assert model["miou"]["avg"] == pytest.approx(sum(model["miou"][h] for h in ("1s", "2s", "3s")) / 3)
    assert metrics["copy_paste"]["l2_at"]["3s"] is None and metrics["copy_paste"]["miou"]["0s"] is None
    assert metrics["constant_velocity"]["miou"]["avg"] is None and metrics["constant_velocity"]["l2_mean"]["3s"] >= 0


def test_exported_weights_give_the_same_forecast(world_ckpt, tmp_path):
    small = tmp_path / "wm.pt"
    size = export_weights(world_ckpt, small)
    assert size < world_ckpt.stat().st_size / 2  # no optimizer state, float16
    full = load_world_model(world_ckpt)
    half = load_world_model(small)
    assert half.world_config.forecaster == "flow" and half.world_config.flow_widths == [8, 8, 8]
    occ = torch.randint(0, 18, (1, 5, 200, 200, 16), dtype=torch.uint8)
    a, b = full.forecast(occ, torch.zeros(1, 4, 2), steps=2), half.forecast(occ, torch.zeros(1, 4, 2), steps=2)
    assert (a.labels == b.labels).float().mean() > 0.99
    torch.testing.assert_close(a.actions, b.actions, atol=1e-2, rtol=1e-2)


def test_forecast_writes_occ3d_labels_and_pictures(world_ckpt, tmp_path):
    root = tmp_path / "occ3d"
    info = export_synthetic(root, "val", 1, 11, progress=False)
    out = tmp_path / "pred"
    assert main(["forecast", "--data", str(root), "--info", str(info), "--ckpt", str(world_ckpt), "--out", str(out),
                 "--pictures", "1"]) == 0
    files = sorted(out.rglob("labels.npz"))
    assert len(files) == 6
    semantics = np.load(files[0])["semantics"]
    assert semantics.shape == (200, 200, 16) and semantics.dtype == np.uint8
    gif = next(out.rglob("forecast.gif"))
    assert Image.open(gif).n_frames == 11 and next(out.rglob("forecast.png")).exists()
    plan = json.loads(next(out.rglob("trajectory.json")).read_text())
    assert len(plan["planned"]) == 6
    page = next(out.rglob("forecast.html"))  # the 3D view of the same forecast
    shown = read_viewer_data(page)["sequences"]["predicted"]
    written = np.stack([np.load(page.parent / f"future_{k}" / "labels.npz")["semantics"] for k in range(1, 7)])
    np.testing.assert_array_equal(shown, written)


def test_demo_runs_on_given_checkpoints(world_ckpt, tmp_path, capsys):
    ckpts = tmp_path / "ckpts"
    ckpts.mkdir()
    export_weights(world_ckpt, ckpts / "wm-small.pt")
    out = tmp_path / "demo"
    assert main(["demo", "--ckpt-dir", str(ckpts), "--out", str(out), "--scenes", "1", "--stride", "29",
                 "--pictures", "1"]) == 0
    assert {"metrics.json", "metrics.md", "pictures"} <= {p.name for p in out.iterdir()}
    gifs = sorted(p.name for p in (out / "pictures").glob("*.gif"))  # the window, and it steered to a stop
    assert gifs == ["synthetic-test-00000-t00-steered-stop.gif", "synthetic-test-00000-t00.gif"]
    index = (out / "index.html").read_text()
    assert 'href="pictures/synthetic-test-00000-t00.html"' in index and "t3former" in index
    assert "<svg" in index and 'src="pictures/synthetic-test-00000-t00.png"' in index
    assert capsys.readouterr().out.rstrip().endswith(f"open {(out / 'index.html').resolve()}")


def test_stage2_rejects_a_missing_autoencoder(tmp_path, capsys):
    ae = tmp_path / "nope.pt"
    assert main(["train-wm", "--config", "small", "--ae", str(ae), f"train.out_dir={tmp_path / 'wm'}"]) == 1
    assert capsys.readouterr().err == f"t3fast train-wm: {ae}: checkpoint not found\n"


def test_rollout_steps_out_of_range(world_ckpt):
    cfg = preset("wm-small-delta")
    cfg.autoencoder_ckpt, cfg.loss.rollout_steps = str(world_ckpt.parent.parent / "ae" / "last.pt"), 7
    planes = Triplane(torch.zeros(1, 11, 8, 8, 6), torch.zeros(1, 11, 8, 8, 2), torch.zeros(1, 11, 8, 6, 2))
    batch = SequenceBatch(torch.zeros(1, 11, 16, 12, 4, dtype=torch.uint8), planes, torch.zeros(1, 4, 2),
                          torch.zeros(1, 6, 2), torch.eye(4).repeat(1, 11, 1, 1))
    with pytest.raises(ValueError, match="rollout_steps"):
        WorldModelTask(cfg).training_step(tiny_world_model(RolloutModel), batch)


def test_pushforward_history_is_the_models_own_forecast():
    """A rollout from step k starts from the model's own k predictions, as at inference: its
    loss equals that of the same step in a full rollout from the present."""
    torch.manual_seed(0)
    model = tiny_world_model(RolloutModel).eval()
    occ = shifting_sequence()
    planes = model.encode_sequence(occ)
    past, future = torch.zeros(1, 4, 2), torch.ones(1, 6, 2)
    cfg = WorldLossConfig(num_occupied=50, num_near_free=20, num_far_free=10, xi=0.0, action_weight=0.0)
    with torch.no_grad():
        pushed = float(rollout_loss(model, planes, occ, past, future, 2, 1, cfg)[1]["triplane"])
        full, _, _ = model(planes.map(lambda p: p[:, :5]), past, steps=3)
        target = planes.map(lambda p: p[:, 7])
        expected = sum(torch.nn.functional.l1_loss(p, t) + torch.nn.functional.mse_loss(p, t)
                       for p, t in zip(full[2], target))
        teacher = rollout_loss(model, planes, occ, past, future, 2, 1, replace(cfg, pushforward=False))[1]
    assert pushed == pytest.approx(float(expected), rel=1e-5)
    assert teacher["triplane"] != pytest.approx(pushed, rel=1e-3)  # ground-truth history differs


def test_rollout_trains_under_autocast():
    """Mixed precision (the trainer's AMP; CPU autocast here): the forecaster's low-precision
    Delta meets the float32 planes in the fused delta op, and the loss and every forecaster
    gradient come out finite."""
    model = tiny_world_model(RolloutModel).train()
    occ = shifting_sequence()
    with torch.no_grad():
        planes = model.encode_sequence(occ)
    cfg = WorldLossConfig(num_occupied=50, num_near_free=20, num_far_free=10)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss, values = rollout_loss(model, planes, occ, torch.zeros(1, 4, 2), torch.ones(1, 6, 2), 0, 6, cfg)
    loss.backward()
    assert torch.isfinite(loss) and all(torch.isfinite(v).all() for v in values.values())
    grads = [p.grad for p in model.forecaster.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert any(bool(g.abs().sum() > 0) for g in grads)


def test_aligned_window_keeps_a_static_world_still():
    # a static world seen by an ego driving 0.8 m (2 voxels) per frame along x: moved into the
    # present frame, every frame shows the present's content wherever that frame saw it
    world = torch.randint(0, 17, (60, 12, 4), dtype=torch.uint8)
    occ = torch.stack([world[2 * t : 2 * t + 16] for t in range(11)])[None]  # frame t sees cells 2t..2t+15
    poses = torch.eye(4).repeat(1, 11, 1, 1)
    poses[0, :, 0, 3] = 0.8 * torch.arange(11.0)
    model = tiny_world_model(RolloutModel)
    planes, moved = ego_aligned_window(model, occ, poses)
    present = occ[0, PRESENT]
    for t in range(11):
        seen = moved[0, t] != 255
        assert torch.equal(moved[0, t][seen], present[seen])
        assert seen.sum() == 12 * 4 * (16 - 2 * abs(t - PRESENT))
    # the future targets are encoded with the present's content where they did not look
    # (batched encodings differ from single ones only by float rounding)
    torch.testing.assert_close(planes.xy[:, -1], model.encode_sequence(occ[:, PRESENT:PRESENT + 1]).xy[:, 0],
                               atol=1e-4, rtol=1e-4)


def test_pushforward_planner_continues_from_its_own_plan():
    """Trained on its own rollouts: the planner's step k sees its own plan of steps 0..k-1,
    so the action loss of a rollout from step 2 is that of step 2 of a full rollout."""
    torch.manual_seed(0)
    model = tiny_world_model(RolloutModel).eval()
    occ = shifting_sequence()
    planes = model.encode_sequence(occ)
    past, future = torch.tensor([[[0.5, 0.0]] * 4]), torch.tensor([[[1.0, 0.2]] * 6])
    cfg = WorldLossConfig(num_occupied=50, num_near_free=20, num_far_free=10, xi=0.0, gamma=0.0)
    with torch.no_grad():
        pushed = float(rollout_loss(model, planes, occ, past, future, 2, 1, cfg)[1]["action"])
        _, full_actions = model(planes.map(lambda p: p[:, :5]), past, steps=3)[:2]
        teacher = rollout_loss(model, planes, occ, past, future, 2, 1, replace(cfg, pushforward=False))[1]["action"]
    assert pushed == pytest.approx(float((full_actions[:, 2] - future[:, 2]).square().sum()), rel=1e-5)
    assert teacher != pytest.approx(pushed, rel=1e-3)


@pytest.mark.slow
def test_paper_preset_trains(tmp_path):
    """Two stage-2 steps at the papers' sizes (full 6-step rollouts, ResNet-18 planner) on tiny data."""
    ae = ["train-ae", "--config", "paper", "train.steps=1", "train.batch_size=1", f"train.out_dir={tmp_path / 'ae'}",
          *TINY_AE]
    assert main(ae) == 0
    wm = ["train-wm", "--config", "paper", "--ae", str(tmp_path / "ae" / "last.pt"), f"train.out_dir={tmp_path / 'wm'}",
          "train.steps=2", "train.batch_size=1", "train.eval_every=0", "train.log_every=1", "data.train_scenes=1",
          "data.frames_per_scene=11", "loss.num_occupied=500", "loss.num_near_free=200", "loss.num_far_free=100"]
    assert main(wm) == 0
    events = [json.loads(line) for line in (tmp_path / "wm" / "metrics.jsonl").read_text().splitlines()]
    assert [e["step"] for e in events if e["event"] == "train"] == [1, 2]
    model = load_world_model(tmp_path / "wm" / "last.pt")
    assert model.world_config.ego_aligned
    assert load_checkpoint(tmp_path / "wm" / "last.pt")["config"]["task"]["loss"]["rollout_steps"] == 6
    assert sum(p.numel() for p in model.parameters()) > 30_000_000


def test_aligned_window_encodes_only_the_frames_a_rollout_reads():
    torch.manual_seed(0)
    occ = torch.randint(0, 18, (1, 11, 16, 12, 4), dtype=torch.uint8)
    poses = torch.eye(4).repeat(1, 11, 1, 1)
    poses[0, :, 0, 3] = 0.8 * torch.arange(11.0)
    model = tiny_world_model(RolloutModel)
    full, moved = ego_aligned_window(model, occ, poses)
    frames = rollout_frames(first=3, steps=1, pushforward=True)
    assert frames == [0, 1, 2, 3, 4, 8]  # the past and present, and the one target
    assert rollout_frames(first=3, steps=1, pushforward=False) == list(range(9))
    some, moved_some = ego_aligned_window(model, occ, poses, frames)
    assert torch.equal(moved, moved_some)
    for a, b in zip(full, some):
        torch.testing.assert_close(b[:, frames], a[:, frames], atol=1e-4, rtol=1e-4)
        others = [t for t in range(11) if t not in frames]
        assert not b[:, others].any()


def test_rows_of_one_model_share_one_forecast_per_window(world_ckpt, monkeypatch):
    """t3former, _gt_ego and _decoded come from one forecasting pass per window, with the same
    scores as three separate passes."""
    model = load_world_model(world_ckpt)
    dataset = SyntheticDriving("test", 1, stride=29)  # 2 windows
    options = dict(gt_ego={"gt_ego": True}, decoded={"keep_static": False}, plan={})
    separate = {name: evaluate_forecasts(t3former_method(model, **kw), dataset, progress=False)
                for name, kw in options.items()}
    passes = []
    forecast = model.forecaster.forward
    monkeypatch.setattr(model.forecaster, "forward", lambda *a, **k: passes.append(1) or forecast(*a, **k))
    shared = SharedRollout(model)
    together = evaluate_many({name: t3former_method(model, shared=shared, **kw) for name, kw in options.items()},
                             dataset, progress=False)
    assert len(passes) == len(dataset) == 2
    assert together == separate


def test_demo_shows_the_ablations_only_when_asked(tmp_path):
    for name in ("wm-small-bev", "wm-small", "unrelated"):
        (tmp_path / f"{name}.pt").touch()
    assert checkpoint_paths(tmp_path, ablations=False) == [tmp_path / "wm-small.pt"]
    assert checkpoint_paths(tmp_path) == [tmp_path / "wm-small.pt", tmp_path / "wm-small-bev.pt"]


def test_a_stage2_step_reads_nothing_on_the_host_as_a_gpu_runs_it():
    """Encoding, the rollout, the sampled decoder loss (fixed-size draws, masked Lovasz and
    cross-entropy) and the backward, as on a GPU (:func:`~t3fast.host_syncs.sync_free`): nothing
    waits for the device (the optimiser's step counters are CPU tensors, outside)."""
    torch.manual_seed(0)
    model = tiny_world_model(RolloutModel).train()
    occ = shifting_sequence()
    past, future = torch.zeros(1, 4, 2), torch.ones(1, 6, 2)
    cfg = WorldLossConfig(num_occupied=50, num_near_free=20, num_far_free=10)
    with sync_free(), SyncCounter() as counter:
        loss, _ = rollout_loss(model, model.encode_sequence(occ), occ, past, future, 2, 1, cfg)
        loss.backward()
    assert counter.total == 0, counter.by_caller
    assert torch.isfinite(loss) and loss > 0


def test_cached_planes_with_their_labels_give_the_labels_path_loss(world_ckpt, tmp_path):
    """``data.cache_labels``: the Delta forecaster's step reads each window's planes from the
    aligned cache and moves its labels in the step: the loss of the labels path, occupancy term
    included, on the planes the step would encode (stored in float16), without the encoder."""
    cfg = preset("wm-small-delta")
    cfg.autoencoder_ckpt = str(world_ckpt.parent.parent / "ae" / "last.pt")
    cfg.model = replace(cfg.model, forecaster_widths=(8, 8, 8), scales=3, max_tokens=64, planner_widths=(8, 8, 8, 8),
                        d_act=20)
    cfg.data = replace(cfg.data, train_scenes=1, frames_per_scene=12, stride=1, cache_dir=str(tmp_path),
                       cache_labels=True)
    cfg.loss = replace(cfg.loss, num_occupied=500, num_near_free=200, num_far_free=100, num_changed=100)
    task = WorldModelTask(cfg)
    model = task.build_model()
    data = task.train_dataset()
    batch = task.collate([data[0], data[1]])
    assert isinstance(batch, SequenceBatch) and batch.planes.xy.shape[:2] == (2, 11)
    encoded, moved = ego_aligned_window(model, batch.occ, batch.ego_poses)
    for cached, fresh in zip(batch.planes, encoded):
        torch.testing.assert_close(cached, fresh, atol=2e-3, rtol=1e-3)  # float16 storage

    def step(planes):
        torch.manual_seed(0)
        return task.training_step(model, replace(batch, planes=planes))

    calls = []
    hook = model.encoder.register_forward_hook(lambda *_: calls.append(1))
    loss, parts = step(batch.planes)
    assert not calls  # no encoder in the step
    expected_loss, expected = step(None)
    hook.remove()
    assert calls
    assert parts["occupancy"] > 0 and set(parts) == set(expected) == {"triplane", "occupancy", "action"}
    for name in parts:
        assert float(parts[name]) == pytest.approx(float(expected[name]), rel=1e-2, abs=1e-4), name
    loss.backward()
    assert all(p.grad is not None for p in model.forecaster.parameters() if p.requires_grad)


def test_cache_labels_needs_the_cached_windows_of_a_delta_forecaster(world_ckpt):
    for changes in ({"latent_cache": False}, {}):
        cfg = preset("wm-small" if not changes else "wm-small-delta")
        cfg.autoencoder_ckpt = str(world_ckpt.parent.parent / "ae" / "last.pt")
        cfg.data = replace(cfg.data, cache_labels=True, **changes)
        with pytest.raises(ConfigError, match="data.cache_labels"):
            WorldModelTask(cfg)


def test_cached_windows_held_in_device_memory_give_the_batches_read_from_disk(world_ckpt, tmp_path):
    """On a GPU where they fit, the labelled windows live in its memory and a batch is gathered
    there: the same batch as the loader's from the cache files (here with the CPU standing in)."""
    cfg = preset("wm-small-delta")
    cfg.autoencoder_ckpt = str(world_ckpt.parent.parent / "ae" / "last.pt")
    cfg.data = replace(cfg.data, train_scenes=2, frames_per_scene=13, stride=1, cache_dir=str(tmp_path),
                       cache_labels=True)
    task = WorldModelTask(cfg)
    task.build_model()
    labelled = task.train_dataset()
    assert isinstance(labelled, LabelledAlignedWindows)  # the CPU reads them from disk
    assert not fits_on(torch.device("cpu"), 1)
    resident = ResidentAlignedWindows(labelled, torch.device("cpu"), progress=False)
    assert len(resident) == len(labelled) == 6
    held = sum(t.numel() * t.element_size() for t in (resident.occ, resident.poses, resident.past_actions,
                                                      resident.future_actions, *resident.planes))
    assert abs(resident_bytes(labelled) - held) <= 0.01 * held
    order = [5, 0, 3]
    got = task.collate(resident.__getitems__(order))
    want = task.collate([labelled[i] for i in order])
    for name in ("occ", "past_actions", "future_actions", "ego_poses"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name
    for a, b in zip(got.planes, want.planes):
        assert torch.equal(a, b)
    loader = torch.utils.data.DataLoader(resident, batch_sampler=[order], collate_fn=task.collate)
    assert torch.equal(next(iter(loader)).occ, want.occ)  # the trainer's loader gathers whole batches


def test_step_variant_draws_the_rollout_start_the_next_step_uses(monkeypatch):
    """``train.cuda_graph`` replays one graph per rollout start: the trainer draws it first
    (``step_variant``) and the step must use that start, not draw another."""
    cfg = preset("wm-small-delta")
    cfg.loss = replace(cfg.loss, rollout_steps=1)
    cfg.data = replace(cfg.data, latent_cache=False)  # the labels path
    task = WorldModelTask.__new__(WorldModelTask)  # the step only: no stage-1 checkpoint to read
    task.cfg = cfg
    used = []
    monkeypatch.setattr("t3fast.training.world_model.task.rollout_loss",
                        lambda model, planes, occ, past, future, first, *rest: used.append(first) or (first, {}))
    model = SimpleNamespace(ego_aligned=False, reads_command=False)
    batch = SequenceBatch(torch.zeros(1, 11, 2, 2, 2), Triplane(torch.zeros(1), None, None), torch.zeros(1, 4, 2),
                          torch.zeros(1, 6, 2), torch.eye(4).expand(1, 11, 4, 4))
    torch.manual_seed(3)
    drawn = []
    for _ in range(12):
        drawn.append(task.step_variant())
        task.training_step(model, batch)
    starts = [d.start for d in drawn]
    assert used == starts and len(set(starts)) > 1 and set(starts) <= set(range(6))
    assert all(d.plan_mirror is None and d.flips is None for d in drawn)  # the labels path has neither
    task.training_step(model, batch)  # without a variant drawn, the step draws its own
    assert len(used) == 13


def test_a_graphed_stage2_run_replays_a_step_that_reads_nothing_on_the_host(world_ckpt, tmp_path, device):
    """``train.cuda_graph`` on the cached labelled windows (the paper preset's path): the trainer
    runs the warm-up steps eagerly, then replays the step; the step it captures reads nothing on
    the host and makes no tensor from host data (as on a GPU: a capture holds neither)."""
    cfg = preset("wm-small-delta")
    cfg.autoencoder_ckpt = str(world_ckpt.parent.parent / "ae" / "last.pt")
    cfg.model = replace(cfg.model, forecaster_widths=(8, 8, 8), scales=3, max_tokens=64, planner_widths=(8, 8, 8, 8),
                        d_act=20)
    cfg.data = replace(cfg.data, train_scenes=1, frames_per_scene=12, stride=1, cache_dir=str(tmp_path / "cache"),
                       cache_labels=True)
    cfg.loss = replace(cfg.loss, num_occupied=300, num_near_free=100, num_far_free=50, num_changed=50,
                       rollout_steps=6, pushforward=True)  # the paper preset's: one start, one graph
    cfg.train = replace(cfg.train, steps=WARMUP + 2, batch_size=1, eval_every=0, ckpt_every=0, log_every=1,
                        tensorboard=False, device=device, out_dir=str(tmp_path / "run"), cuda_graph=True)
    trainer = Trainer(WorldModelTask(cfg), cfg.train)
    trainer.fit()
    assert trainer.graphed.report() == {"graphs": 1, "replays": 2, "eager_steps": WARMUP, "failures": {}}
    batch = next(iter(trainer.loader)).to(device)
    trainer.task.cfg.loss = replace(cfg.loss, rollout_steps=2)  # a later start: history pushed forward
    while trainer.task.step_variant().start == 0:
        pass
    with sync_free(), SyncCounter() as counter:
        terms = trainer.graphed.body(batch)
    assert counter.total == 0, counter.by_caller
    assert not counter.host_data, counter.host_data
    assert all(torch.isfinite(v) for v in terms.values()) and set(terms) >= {"loss", "occupancy", "grad_norm"}


def _flow_task(world_ckpt, cache_dir, **train) -> WorldModelTask:
    """The shipped preset's stage 2, tiny: the flow forecaster and the route planner on the cached
    latent windows of one scene, mirrored and flipped at random."""
    cfg = preset("wm-small")
    cfg.autoencoder_ckpt = str(world_ckpt.parent.parent / "ae" / "last.pt")
    cfg.model = replace(cfg.model, flow_widths=(8, 8, 8))
    cfg.data = replace(cfg.data, train_scenes=1, frames_per_scene=14, stride=1, cache_dir=str(cache_dir))
    cfg.train = replace(cfg.train, batch_size=2, eval_every=0, ckpt_every=0, log_every=1, tensorboard=False,
                        **train)
    return WorldModelTask(cfg)


@pytest.fixture(scope="module")
def flow_cache(tmp_path_factory):
    """The cache folder the tiny shipped-preset tasks share (their windows encoded once)."""
    return tmp_path_factory.mktemp("flow-cache")


def test_the_latent_windows_held_whole_give_the_loaders_batches_and_as_on_a_gpu_the_same_loss(world_ckpt, flow_cache):
    """Held whole (on a GPU where they fit), the cached latent windows give the batches the loader
    collates from their files; as on a GPU (no host read) every window's boxes are padded to the
    split's most agents, so all batches have one shape, and the padding changes no loss term."""
    task = _flow_task(world_ckpt, flow_cache)
    model = task.build_model()
    cache = task.train_dataset()
    assert isinstance(cache, AlignedLatentCache)  # the CPU reads them from disk
    held = AlignedBatches(cache, progress=False)
    assert len(held) == len(cache) == 4 and cache.stored_bytes() >= nbytes(held.fields) * 0.9
    agents = [cache[i].boxes.shape[1] for i in range(len(cache))]
    order = [agents.index(min(agents)), 2]
    got, want = task.collate(held.__getitems__(order)), task.collate([cache[i] for i in order])
    for a, b in zip(dataclasses.astuple(got), dataclasses.astuple(want)):
        for x, y in zip(a if isinstance(a, Triplane) else [a], b if isinstance(b, Triplane) else [b]):
            assert (x is None and y is None) or torch.equal(x, y)
    with sync_free():
        padded = held.take(torch.tensor([order[0]]))
    assert padded.boxes.shape[2] == max(agents) > min(agents)
    trimmed = held.take(torch.tensor([order[0]]))
    with torch.no_grad():
        for a, b in zip(motion_loss(model, padded, task.cfg.loss)[1].values(),
                        motion_loss(model, trimmed, task.cfg.loss)[1].values()):
            torch.testing.assert_close(a, b)


def test_the_shipped_presets_stage2_step_replays_and_reads_nothing_on_the_host(world_ckpt, flow_cache, tmp_path,
                                                                               device):
    """``train.cuda_graph`` on the cached latent windows, held whole as on a GPU: the trainer
    draws each step's mirror and flips first (``step_variant``), replays one graph per variant,
    and the step it captures reads nothing on the host and makes no tensor from host data."""
    task = _flow_task(world_ckpt, flow_cache, steps=4, device=device, out_dir=str(tmp_path / "run"), cuda_graph=True)
    variants = [StepChoices(True, (True, False, True), None), StepChoices(False, (False, True, False), None)]
    calls = itertools.count()

    def two_variants() -> StepChoices:
        task._drawn = variants[next(calls) % 2]
        return task._drawn

    original = task.train_dataset

    def held() -> AlignedBatches:  # as on a GPU where they fit: one batch shape
        data = original()
        return data if isinstance(data, AlignedBatches) else AlignedBatches(data, device, progress=False)

    drawn, task.train_dataset = task.step_variant, held
    trainer = Trainer(task, task.cfg.train)
    assert drawn().plan_mirror is not None and len(task._drawn.flips) == 3 and task._drawn.start is None
    task.step_variant = two_variants
    trainer.graphed.warmup = 1
    with sync_free():
        trainer.fit()
    assert trainer.graphed.report() == {"graphs": 2, "replays": 2, "eager_steps": 2, "failures": {}}
    batch = next(iter(trainer.loader)).to(device)
    task.step_variant()
    with sync_free(), SyncCounter() as counter:
        terms = trainer.graphed.body(batch)
    assert counter.total == 0, counter.by_caller
    assert not counter.host_data, counter.host_data
    assert all(torch.isfinite(v) for v in terms.values()) and {"loss", "plan_l2"} <= set(terms)
