"""The route planner trained on its own: its cache reads what inference encodes, mirroring is
consistent, it learns, and ``train-planner`` -> eval works end to end."""

from __future__ import annotations

import json

import pytest
import torch

from t3fast.commands.main import main
from t3fast.data.route import LEFT, RIGHT, STRAIGHT
from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import ConfigError
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.io.checkpoint import load_checkpoint
from t3fast.models.ego_motion import planar_poses
from t3fast.models.planner import constant_turn_rate
from t3fast.pretrained import load_world_model
from t3fast.training.configs import PlannerConfig
from t3fast.training.planner.plan_cache import PlanCache, PlanWindows
from t3fast.training.planner.task import PlannerTask, mirror_left_right, plan_summary
from t3fast.training.world_model.plan_loss import plan_error

from .tiny_runs import TINY_PLAN


def _windows(n: int = 3, seed: int = 0) -> PlanWindows:
    g = torch.Generator().manual_seed(seed)
    future = torch.randn(n, 6, 2, generator=g)
    return PlanWindows(torch.randn(n, 8, 10, 10, generator=g), torch.randn(n, 8, 10, 10, generator=g),
                       torch.randn(n, 4, 2, generator=g), future, torch.tensor([RIGHT, LEFT, STRAIGHT])[:n])


def test_the_cache_holds_the_planes_inference_encodes(world_ckpt, tmp_path):
    model = load_world_model(world_ckpt)
    windows = SyntheticDriving("train", 1, 13, stride=2)
    cache = PlanCache(windows, model, tmp_path)
    assert cache.build(progress=False) == 1 and cache.build(progress=False) == 0  # resumable: nothing left
    batch = cache.all()
    assert len(cache) == len(windows) == 2
    for i in range(len(windows)):
        sample = windows[i]
        poses = planar_poses(sample.ego_poses[None], PRESENT)[:, : PRESENT + 1]
        planes = model.pipeline.encode.planes(sample.occ[None, : PRESENT + 1], poses).xy[0]
        torch.testing.assert_close(batch.present[i], planes[-1], atol=2e-3, rtol=0)  # stored in float16
        torch.testing.assert_close(batch.previous[i], planes[-2], atol=2e-3, rtol=0)
        torch.testing.assert_close(batch.future_actions[i], sample.future_actions)
        assert batch.command[i] == sample.command


def test_a_cache_without_planes_encodes_nothing_and_holds_the_same_motion(world_ckpt, tmp_path, monkeypatch):
    model = load_world_model(world_ckpt)
    windows = SyntheticDriving("train", 1, 13, stride=2)
    full = PlanCache(windows, model, tmp_path)
    full.build(progress=False)
    monkeypatch.setattr("t3fast.forecast.encode.encode_sequence", lambda *a: pytest.fail("encoded a frame"))
    motion = PlanCache(windows, model, tmp_path, planes=False)
    assert motion.root != full.root and motion.build(progress=False) == 1
    a, b = full.all(), motion.all()
    assert b.present.shape == (2, 0, 1, 1)
    torch.testing.assert_close(a.past_actions, b.past_actions)
    torch.testing.assert_close(a.future_actions, b.future_actions)
    assert torch.equal(a.command, b.command)


def test_a_cache_missing_a_scene_says_so(world_ckpt, tmp_path):
    cache = PlanCache(SyntheticDriving("train", 1, 12), load_world_model(world_ckpt), tmp_path)
    with pytest.raises(FileNotFoundError, match="1 scenes are not cached"):
        cache.all()


def test_mirroring_twice_is_the_identity_and_swaps_turns():
    batch = _windows()
    once = mirror_left_right(batch)
    assert once.command.tolist() == [LEFT, RIGHT, STRAIGHT]
    torch.testing.assert_close(once.future_actions[..., 1], -batch.future_actions[..., 1])
    torch.testing.assert_close(once.present, batch.present.flip(-1))
    twice = mirror_left_right(once)
    for a, b in zip(twice.inputs(), batch.inputs()):
        torch.testing.assert_close(a, b)


def test_plan_summary_follows_the_evaluation_conventions():
    errors = torch.arange(1.0, 7.0)[None].repeat(2, 1)  # 1..6 m at steps 1..6
    summary = plan_summary(errors)
    assert summary["l2_3s"] == 6.0
    assert summary["l2_mean"] == pytest.approx((1.5 + 2.5 + 3.5) / 3)
    assert plan_error(torch.ones(1, 6, 2), torch.ones(1, 6, 2)).abs().max() == 0


def test_the_planner_learns_the_windows_it_sees(world_ckpt):
    """A few hundred steps on four windows bring the plan well below constant turn rate's error
    on them: the path from the cached planes to the planner's loss carries gradients."""
    torch.manual_seed(0)
    model = load_world_model(world_ckpt).train()
    planner = model.planner
    c, h, w = model.encoder.config.channels, *model.encoder.config.plane_shape[:2]
    g = torch.Generator().manual_seed(1)
    past = torch.tensor([[1.0, 0.0]] * 4).expand(4, 4, 2)
    future = past[:, :1] * torch.rand(4, 1, 1, generator=g) * 2 + torch.randn(4, 6, 2, generator=g) * 0.3
    batch = PlanWindows(torch.randn(4, c, h, w, generator=g), torch.randn(4, c, h, w, generator=g), past, future,
                        torch.full((4,), STRAIGHT))
    base = plan_error(constant_turn_rate(past, 6), future).mean()
    opt = torch.optim.Adam(planner.parameters(), lr=1e-3)
    for _ in range(200):
        loss = plan_error(planner.candidates(*batch.inputs())[0][:, 0], future).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert loss < 0.3 * base
    assert all(p.grad is None for p in model.forecaster.parameters())


def test_train_planner_retrains_only_the_planner_and_its_checkpoints_are_world_models(world_ckpt, tmp_path, capsys):
    out = tmp_path / "plan"
    args = ["train-planner", "--wm", str(world_ckpt), f"data.cache_dir={tmp_path / 'cache'}",
            f"train.out_dir={out}", *TINY_PLAN]
    assert main([*args, "train.steps=2"]) == 0
    assert main([*args, "train.steps=3", "--resume"]) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 3
    events = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    evals = [e for e in events if e["event"] == "eval"]
    assert [e["step"] for e in evals] == [0, 2, 3]
    assert evals[0]["values"]["command_l2_mean_ratio"] == pytest.approx(1.0, abs=0.01)  # new: constant turn rate
    assert {"no_command_l2_3s", "ctr_l2_mean", "command_l2_mean_ratio", "score"} <= set(evals[-1]["values"])
    before, after = load_world_model(world_ckpt).state_dict(), load_world_model(out / "last.pt").state_dict()
    kept = [k for k in before if not k.startswith("planner.")]
    assert kept and all(torch.equal(before[k], after[k]) for k in kept)
    assert load_world_model(out / "last.pt").planner.scene is None  # the preset's planner: past motion and command
    capsys.readouterr()
    assert main(["eval", str(out / "last.pt"), "--scenes", "1", "--stride", "29", "--out", str(tmp_path / "ev")]) == 0
    assert "t3former_command" in json.loads((tmp_path / "ev" / "metrics.json").read_text())


def test_train_planner_refuses_a_world_model_without_a_route_planner(world_ckpt, tmp_path):
    state = load_checkpoint(world_ckpt)
    state["config"]["task"]["model"]["planner"] = "phi_act"
    torch.save(state, tmp_path / "phi.pt")
    with pytest.raises(ConfigError, match="trains a route planner"):
        PlannerTask(PlannerConfig(world_model=str(tmp_path / "phi.pt")))


def test_command_dropout_outside_a_share_is_refused():
    with pytest.raises(ConfigError, match="command_dropout"):
        PlannerConfig(command_dropout=1.5)


def test_a_planner_without_the_scene_reads_only_the_past_motion_and_the_command(world_ckpt, tmp_path):
    cfg = PlannerConfig(world_model=str(world_ckpt), scene=False)
    model = PlannerTask(cfg).build_model()
    assert model.planner.scene is None and model.world_config.route_scene is False
    torch.nn.init.normal_(model.planner.head[-1].weight)
    batch = _windows(n=3)
    other = PlanWindows(torch.randn_like(batch.present), torch.randn_like(batch.previous), batch.past_actions,
                        batch.future_actions, batch.command)
    torch.testing.assert_close(model.planner(*batch.inputs()), model.planner(*other.inputs()))
    assert not torch.allclose(model.planner(*batch.inputs()), model.planner(*batch.inputs()[:3], None))


def test_a_planner_of_several_modes_plans_its_best_scored_mode_and_trains_each_on_the_futures_it_wins(world_ckpt):
    task = PlannerTask(PlannerConfig(world_model=str(world_ckpt), scene=False, modes=3))
    model = task.build_model().train()
    planner = model.planner
    batch = _windows(n=3)
    plans, scores = model(*batch.inputs())
    assert plans.shape == (3, 3, 6, 2) and scores.shape == (3, 3)
    ctr = constant_turn_rate(batch.past_actions, 6)
    torch.testing.assert_close(plans, ctr.unsqueeze(1).expand_as(plans), atol=0.05, rtol=0)  # untrained: about it
    with torch.no_grad():
        planner.head[-1].bias[-3:] = torch.tensor([0.0, 5.0, 0.0])  # mode 1 scores best
    torch.testing.assert_close(planner(*batch.inputs()), model(*batch.inputs())[0][:, 1])
    with SyncCounter() as counter:  # the logged values are read by the trainer after the backward
        loss, values = task.training_step(model, batch)
        mirror_left_right(batch)  # whichever way the step's coin fell
    # the one value read is the mirror's coin toss, from a CPU generator: no wait on a GPU
    assert dict(counter.by_caller) == {"training/step_draws.py:toss": 1}
    assert not counter.host_data, counter.host_data  # the mirror's signs are device constants
    task.step_variant()  # train.cuda_graph: the toss drawn first, the step as a graph holds it
    with sync_free(), SyncCounter() as graphed:
        task.training_step(model, batch)[0].backward()
    assert graphed.total == 0 and not graphed.host_data, (graphed.by_caller, graphed.host_data)
    assert {"closest_l2", "mode_choice"} <= set(values) and torch.isfinite(loss)
    loss.backward()
    assert planner.head[-1].weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in model.forecaster.parameters())
