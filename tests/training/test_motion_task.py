"""The motion head trained on its own: its cache holds what inference measures and what the
world-model loss compares, mirroring keeps the errors, it learns, and ``train-motion`` -> eval
works end to end."""

from __future__ import annotations

import json

import pytest
import torch

from t3fast.commands.main import main
from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import ConfigError
from t3fast.forecast.agents import measured_velocities
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.io.checkpoint import load_checkpoint
from t3fast.models.ego_motion import planar_poses
from t3fast.models.flow_forecaster import tracker_motion
from t3fast.models.triplane import Triplane
from t3fast.pretrained import load_world_model
from t3fast.training.configs import MotionConfig
from t3fast.training.motion.motion_cache import MotionCache, MotionWindows
from t3fast.training.motion.task import MotionHeadTraining, MotionTask, mirror_left_right, motion_head_loss
from t3fast.training.world_model.motion_loss import AgentTargets, agent_errors, agent_targets, flow_terms
from t3fast.training.world_model.motion_targets import agent_motion

from .tiny_runs import TINY_MOTION


@pytest.fixture(scope="module")
def cached(world_ckpt, tmp_path_factory):
    """A tiny world model and the motion cache of one scene's two windows."""
    model = load_world_model(world_ckpt)
    windows = SyntheticDriving("train", 1, 13, stride=2)
    cache = MotionCache(windows, model, tmp_path_factory.mktemp("motion-cache"))
    assert cache.build(progress=False) == 1 and cache.build(progress=False) == 0  # resumable: nothing left
    return model, windows, cache


def test_the_cache_holds_the_velocities_inference_measures_and_the_losses_targets(cached):
    model, windows, cache = cached
    batch = cache.all()
    assert len(cache) == len(windows) == 2 and batch.velocity.shape[0] == 2
    for i in range(len(windows)):
        sample = windows[i]
        poses = planar_poses(sample.ego_poses[None], PRESENT)[:, : PRESENT + 1]
        velocity = measured_velocities(sample.occ[None, : PRESENT + 1], poses, model.encoder.config.plane_shape[:2])
        torch.testing.assert_close(batch.velocity[i : i + 1], velocity)
        planes = model.pipeline.encode.planes(sample.occ[None, : PRESENT + 1], poses).xy[0]
        torch.testing.assert_close(batch.present[i], planes[-1], atol=2e-3, rtol=0)
        target, moving, static, _, covered, owner = agent_motion(sample.boxes[None], sample.box_valid[None])
        expected = agent_targets(target, moving, static, covered, owner, velocity, sample.boxes.shape[1])
        a = min(expected.motion.shape[2], batch.targets.motion.shape[2])  # the cache trims boxes no cell is of
        assert torch.equal(batch.targets.cells[i], expected.cells[0])
        assert torch.equal(batch.targets.visible[i, :, :a], expected.visible[0, :, :a])
        assert not batch.targets.visible[i, :, a:].any() and not expected.visible[0, :, a:].any()  # padding
        torch.testing.assert_close(batch.targets.motion[i, :, :a], expected.motion[0, :, :a])
    assert batch.targets.visible.any(), "the scene's windows should hold tracked agents"


def test_the_heads_forward_is_the_forecasters_motion(cached):
    model, _, cache = cached
    batch = cache.all()
    torch.nn.init.normal_(model.forecaster.motion_head.head[-1].weight, std=0.1)  # a head that corrects
    alone = MotionHeadTraining.forward(model, batch.velocity, batch.present, batch.previous)
    past = Triplane(torch.stack([batch.previous, batch.previous, batch.previous, batch.previous, batch.present], 1),
                    None, None)
    _, displacements, _ = model.forecaster.predict(past, batch.velocity)
    torch.testing.assert_close(alone, displacements)
    assert not torch.allclose(alone, tracker_motion(batch.velocity, alone.shape[1]))


def test_a_batch_made_as_on_a_gpu_keeps_every_padded_agent_and_the_same_loss(cached, world_ckpt):
    """Where the host may not read (a GPU), a batch keeps every agent the split pads to (its
    shapes do not depend on its data); on the CPU it keeps those its cells name. The padded
    agents are never visible: the loss is the same."""
    _, _, cache = cached
    batches = cache.batches()
    task = MotionTask(MotionConfig(world_model=str(world_ckpt)))
    model = task.build_model()
    torch.nn.init.normal_(model.forecaster.motion_head.head[-1].weight, std=0.1)
    trimmed_any = False
    for i in range(len(batches)):
        index = torch.tensor([i])
        trimmed = batches.take(index)
        with sync_free():
            padded = batches.take(index)
        assert padded.targets.motion.shape[2] == batches.fields["motion"].shape[2]
        trimmed_any |= trimmed.targets.motion.shape[2] < padded.targets.motion.shape[2]
        displacements = model(trimmed.velocity, trimmed.present, trimmed.previous)
        torch.testing.assert_close(motion_head_loss(displacements, padded.targets, task.cfg),
                                   motion_head_loss(displacements, trimmed.targets, task.cfg))
    assert trimmed_any, "a window with fewer agents than the split's most should be trimmed on the CPU"


def test_a_missing_scene_is_named(world_ckpt, tmp_path):
    cache = MotionCache(SyntheticDriving("train", 1, 12), load_world_model(world_ckpt), tmp_path)
    with pytest.raises(FileNotFoundError, match="1 scenes are not cached"):
        cache.all()


def _random_windows(seed: int = 0) -> tuple[MotionWindows, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    cells = torch.randint(-1, 3, (2, 6, 7), generator=g)
    targets = AgentTargets(cells, torch.rand(2, 4, 3, generator=g) > 0.2, torch.randn(2, 4, 3, 2, generator=g) * 2)
    velocity = torch.randn(2, 4, 6, 7, generator=g) * (cells >= 0)[:, None]
    batch = MotionWindows(torch.randn(2, 8, 6, 7, generator=g), torch.randn(2, 8, 6, 7, generator=g), velocity, targets)
    return batch, torch.randn(2, 4, 2, 6, 7, generator=g)


def test_mirroring_keeps_every_agents_error_and_twice_is_the_identity():
    batch, displacements = _random_windows()
    mirrored = mirror_left_right(batch)
    sign = torch.tensor([1.0, -1.0]).view(1, 1, 2, 1, 1)
    flipped = displacements.flip(-1) * sign
    for a, b in zip(agent_errors(displacements, batch.targets), agent_errors(flipped, mirrored.targets)):
        torch.testing.assert_close(a, b)
    torch.testing.assert_close(tracker_motion(mirrored.velocity, 4), tracker_motion(batch.velocity, 4).flip(-1) * sign)
    twice = mirror_left_right(mirrored)
    for a, b in ((twice.present, batch.present), (twice.velocity, batch.velocity), (twice.targets.cells,
                 batch.targets.cells), (twice.targets.motion, batch.targets.motion)):
        assert torch.equal(a, b)


def test_an_agents_error_is_its_mean_displacement_against_its_motion():
    cells = torch.tensor([[[0, 0, -1], [1, -1, -1]]])  # agent 0 on two cells, agent 1 on one
    targets = AgentTargets(cells, torch.tensor([[[True, True]]]), torch.tensor([[[[2.0, 0.0], [0.1, 0.1]]]]))
    displacements = torch.zeros(1, 1, 2, 2, 3)
    displacements[0, 0, 0, 0, :2] = torch.tensor([1.0, 2.0])  # agent 0 moves 1.5 cells on average along x
    error, moving, parked = agent_errors(displacements, targets)
    torch.testing.assert_close(error, torch.tensor([[[0.5, 0.2]]]))
    assert moving.tolist() == [[[True, False]]] and parked.tolist() == [[[False, True]]]
    torch.testing.assert_close(torch.stack(flow_terms(displacements, targets)), torch.tensor([0.5, 0.2]))


def test_the_head_learns_the_windows_it_sees(cached, world_ckpt):
    """Steps on the cached windows bring the agents' error clearly below the tracker's: the path
    from the cached inputs to the per-agent loss carries gradients to the head alone."""
    _, _, cache = cached
    torch.manual_seed(0)
    task = MotionTask(MotionConfig(world_model=str(world_ckpt)))
    model = task.build_model().train()
    batch = cache.all()
    tracker = sum(flow_terms(tracker_motion(batch.velocity, 6), batch.targets))
    opt = torch.optim.Adam(model.forecaster.motion_head.parameters(), lr=3e-3)
    with SyncCounter() as counter:  # the logged values are read by the trainer after the backward
        task.training_step(model, batch)
        mirror_left_right(batch)  # whichever way the step's coin fell
    # the one value read is the mirror's coin toss, from a CPU generator: no wait on a GPU
    assert dict(counter.by_caller) == {"training/step_draws.py:toss": 1}
    assert not counter.host_data, counter.host_data  # the mirror's signs are device constants
    task.step_variant()  # train.cuda_graph: the toss drawn first, the step as a graph holds it
    with sync_free(), SyncCounter() as graphed:
        task.training_step(model, batch)
    assert graphed.total == 0 and not graphed.host_data, (graphed.by_caller, graphed.host_data)
    for _ in range(200):
        loss, _ = task.training_step(model, batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    final = sum(flow_terms(model(batch.velocity, batch.present, batch.previous),
                           batch.targets))
    assert final < 0.8 * tracker
    assert all(p.grad is None for n, p in model.named_parameters() if "motion_head" not in n)


def test_train_motion_retrains_only_the_motion_head_and_its_checkpoints_are_world_models(world_ckpt, tmp_path, capsys):
    out = tmp_path / "motion"
    args = ["train-motion", "--wm", str(world_ckpt), f"data.cache_dir={tmp_path / 'cache'}",
            f"train.out_dir={out}", *TINY_MOTION]
    assert main([*args, "train.steps=2"]) == 0
    assert main([*args, "train.steps=3", "--resume"]) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 3
    events = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    evals = [e for e in events if e["event"] == "eval"]
    assert [e["step"] for e in evals] == [0, 2, 3]
    assert evals[0]["values"]["ratio_moving"] == pytest.approx(1.0)  # new: the tracker
    assert {"head_moving_3s", "tracker_parked", "ratio_parked", "score"} <= set(evals[-1]["values"])
    before, after = load_world_model(world_ckpt).state_dict(), load_world_model(out / "last.pt").state_dict()
    kept = [k for k in before if "motion_head" not in k]
    assert kept and all(torch.equal(before[k], after[k]) for k in kept)
    capsys.readouterr()
    assert main(["eval", str(out / "last.pt"), "--scenes", "1", "--stride", "29", "--out", str(tmp_path / "ev")]) == 0
    assert "t3former_gt_ego" in json.loads((tmp_path / "ev" / "metrics.json").read_text())


def test_train_motion_refuses_a_world_model_without_a_motion_head(tmp_path):
    with pytest.raises(ConfigError, match="'wm-small-no-delta' has no motion head to train"):
        MotionTask(MotionConfig(world_model="wm-small-no-delta"))


def test_the_motion_cache_needs_a_flow_forecaster(tmp_path):
    with pytest.raises(ValueError, match="the model needs a flow forecaster"):
        MotionCache(SyntheticDriving("train", 1, 13, stride=2), load_world_model("wm-small-no-delta"), tmp_path)


def test_a_negative_parked_weight_is_refused():
    with pytest.raises(ConfigError, match="parked_weight"):
        MotionConfig(parked_weight=-1.0)



def test_the_precision_term_is_zero_when_exact_and_its_weight_when_far_off():
    batch, _ = _random_windows()
    t = batch.targets
    index = t.cells.clamp(min=0)[:, None, :, :, None].expand(-1, 4, -1, -1, 2)  # [B, S, H, W, 2]
    exact = t.motion[:, :, None].expand(-1, -1, 6, -1, -1).gather(3, index).permute(0, 1, 4, 2, 3)
    exact = exact * (t.cells >= 0)[:, None, None]
    cfg = MotionConfig(precision_weight=2.0, precision_scale=0.5)
    _, parts = motion_head_loss(exact, t, cfg)
    assert parts["miss"] == pytest.approx(0.0, abs=1e-6) and parts["flow_moving"] == pytest.approx(0.0, abs=1e-5)
    loss, parts = motion_head_loss(exact + 10.0, t, cfg)
    assert parts["miss"] == pytest.approx(1.0)
    assert float(loss) == pytest.approx(parts["flow_moving"] + parts["flow_parked"] + 2.0)


def test_a_bad_precision_scale_is_refused():
    with pytest.raises(ConfigError, match="precision_scale"):
        MotionConfig(precision_scale=0.0)
