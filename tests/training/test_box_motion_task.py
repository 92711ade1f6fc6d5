"""The box motion network trained on its own: its records hold what inference computes and the
true future boxes, mirroring keeps the errors, the loss counts every class alike, it learns, and
``train-box-motion`` -> eval works end to end."""

from __future__ import annotations

import json

import pytest
import torch

from t3fast.agents.box_kinematics import BOX_CLASSES, STILL_STEP, ego_step
from t3fast.commands.main import main
from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.errors import ConfigError
from t3fast.forecast.agents import fitted_boxes
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.io.checkpoint import load_checkpoint
from t3fast.models.box_motion import BoxMotionNet, predict_box_poses
from t3fast.models.ego_motion import planar_poses, rotate
from t3fast.pretrained import load_world_model
from t3fast.training.box_motion.box_cache import BoxCache, BoxMotionSamples, window_record
from t3fast.training.box_motion.loss import class_balanced_mean, landing_errors
from t3fast.training.box_motion.task import BoxMotionTask, agent_errors, mirror_agents
from t3fast.training.configs import BoxMotionConfig

from .tiny_runs import TINY_BOX


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    """The records of one scene's four windows, built once and then read back."""
    windows = SyntheticDriving("train", 1, 14, stride=1)
    root = tmp_path_factory.mktemp("box-cache")
    cache = BoxCache(windows, root)
    built = cache.records(progress=False)
    stamp = cache.path(0).stat().st_mtime_ns
    again = BoxCache(windows, root).records(progress=False)
    assert cache.path(0).stat().st_mtime_ns == stamp and len(again) == len(built) == 4  # read, not rebuilt
    for a, b in zip(built, again):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    return windows, again


def test_a_record_holds_what_inference_fits_and_the_true_future(records, world_ckpt):
    windows, recs = records
    model = load_world_model(world_ckpt)
    model.box_motion = BoxMotionNet()
    sample = windows[2]
    poses = planar_poses(sample.ego_poses[None], PRESENT)[:, : PRESENT + 1]
    boxes, ids, _ = fitted_boxes(sample.occ[None, : PRESENT + 1], poses)
    fit = boxes[0]
    fit.future = predict_box_poses(model.box_motion, sample.occ[PRESENT], fit, ids[0], ego_step(poses[0]))
    record = recs[2]
    assert record["centre"].shape[0] > 0, "the window should hold agents drawn as boxes"
    for i in range(record["centre"].shape[0]):
        a = int((fit.centre.float() - record["centre"][i]).norm(dim=-1).argmin())
        torch.testing.assert_close(fit.centre[a].float(), record["centre"][i])
        torch.testing.assert_close(fit.velocity[a].float(), record["velocity"][i])
        # the untrained network moves it at its fitted velocity, as the record's prediction at zero
        # does, unless it stands
        k = torch.arange(1, 7, dtype=torch.float64)[:, None] * float(fit.velocity[a].norm() >= STILL_STEP)
        torch.testing.assert_close(fit.future[:, a, :2], fit.centre[a] + k * fit.velocity[a])
        # the target is the nearest true box's motion
        boxes = sample.boxes.double()
        j = int((boxes[PRESENT, :, :2] - fit.centre[a]).norm(dim=-1).masked_fill(~sample.box_valid[PRESENT],
                                                                                    1e9).argmin())
        valid = record["valid"][i]
        torch.testing.assert_close(record["displacement"][i][valid],
                                   (boxes[PRESENT + 1 :, j, :2] - boxes[PRESENT, j, :2])[valid].float())


def test_mirroring_keeps_every_agents_error_and_twice_is_the_identity(records):
    _, recs = records
    samples = BoxMotionSamples(recs)
    batch = samples.all()
    batch["views"] = batch["views"].float()
    flip = torch.arange(len(samples)) % 2 == 0
    torch.manual_seed(0)
    correction = torch.randn(len(samples), 6, 3)
    mirrored = mirror_agents(batch, flip)
    flipped = torch.where(flip[:, None, None], correction * torch.tensor([1.0, -1.0, -1.0]), correction)
    torch.testing.assert_close(agent_errors(flipped, mirrored), agent_errors(correction, batch))
    twice = mirror_agents(mirrored, flip)
    for key in ("views", "features", "velocity", "displacement", "turn"):  # float32: a few ulps of the larger ones
        torch.testing.assert_close(twice[key], batch[key], atol=1e-5, rtol=1e-6)


def test_the_error_counts_the_centre_and_the_heading_and_every_class_alike():
    n = 3
    fields = {"displacement": torch.zeros(n, 1, 2), "turn": torch.zeros(n, 1),
              "valid": torch.ones(n, 1, dtype=torch.bool), "features": torch.zeros(n, 5 + len(BOX_CLASSES))}
    fields["features"][:, -2] = 4.0  # 4 m long
    fields["features"][0, -2 - len(BOX_CLASSES)] = 1  # one agent of the first class, two of the second
    fields["features"][1:, -1 - len(BOX_CLASSES)] = 1
    displacement = torch.tensor([[[3.0, 4.0]], [[0.0, 0.0]], [[0.0, 1.0]]])
    turn = torch.tensor([[0.0], [0.5], [0.0]])
    errors = landing_errors(displacement, turn, fields)
    torch.testing.assert_close(errors, torch.tensor([[5.0], [1.0], [1.0]]))  # 0.5 rad at 2 m
    torch.testing.assert_close(class_balanced_mean(errors, fields), torch.tensor(3.0))  # (5 + (1 + 1) / 2) / 2
    fields["valid"][0] = False  # the first class has no valid step left: only the second counts
    torch.testing.assert_close(class_balanced_mean(errors, fields), torch.tensor(1.0))


def test_the_network_learns_the_agents_it_sees(records, world_ckpt):
    """Steps on one scene's agents bring their landing error clearly below the box tracker's:
    the path from the cached views and kinematics to the loss carries gradients to the network
    alone."""
    _, recs = records
    torch.manual_seed(0)
    task = BoxMotionTask(BoxMotionConfig(world_model=str(world_ckpt)))
    model = task.build_model().train()
    samples = BoxMotionSamples(recs)
    batch = samples.all()
    tracker = class_balanced_mean(agent_errors(torch.zeros(len(samples), 6, 3), batch), batch)
    opt = torch.optim.Adam(model.box_motion.parameters(), lr=3e-3)
    with SyncCounter() as counter:  # the logged values are read by the trainer after the backward
        task.training_step(model, batch)
    assert counter.total == 0, counter.by_caller
    assert not counter.host_data, counter.host_data  # the mirror's signs are device constants
    assert task.step_variant() is None  # train.cuda_graph: no host choice, the agents to mirror drawn on the device
    with sync_free(), SyncCounter() as graphed:
        task.training_step(model, batch)
    assert graphed.total == 0 and not graphed.host_data, (graphed.by_caller, graphed.host_data)
    for _ in range(150):
        loss, values = task.training_step(model, batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert values["tracker"] > 0
    with torch.no_grad():
        correction = model(batch["views"].float(), batch["features"])
    assert class_balanced_mean(agent_errors(correction, batch), batch) < 0.7 * tracker
    assert all(p.grad is None for n, p in model.named_parameters() if not n.startswith("box_motion."))


def test_train_box_motion_trains_only_the_network_and_its_checkpoints_are_world_models(world_ckpt, tmp_path, capsys):
    out = tmp_path / "box"
    args = ["train-box-motion", "--wm", str(world_ckpt), f"data.cache_dir={tmp_path / 'cache'}",
            f"train.out_dir={out}", *TINY_BOX]
    assert main([*args, "train.steps=2", "train.eval_at_start=true"]) == 0
    assert main([*args, "train.steps=3", "train.eval_at_start=true", "--resume"]) == 0
    assert load_checkpoint(out / "last.pt")["step"] == 3
    evals = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    evals = [e for e in evals if e["event"] == "eval"]
    assert [e["step"] for e in evals] == [0, 2, 3]
    assert evals[0]["values"]["ratio"] == pytest.approx(1.0)  # new: the box tracker
    assert {"net_3s", "tracker_1s", "score"} <= set(evals[-1]["values"])
    before, after = load_world_model(world_ckpt).state_dict(), load_world_model(out / "last.pt")
    assert after.world_config.box_motion and after.box_motion is not None
    assert all(torch.equal(v, after.state_dict()[k]) for k, v in before.items())
    capsys.readouterr()
    assert main(["eval", str(out / "last.pt"), "--scenes", "1", "--stride", "29", "--out", str(tmp_path / "ev")]) == 0
    assert "t3former_gt_ego" in json.loads((tmp_path / "ev" / "metrics.json").read_text())


def test_train_box_motion_refuses_a_world_model_without_boxes(world_ckpt, tmp_path):
    state = load_checkpoint(world_ckpt)
    state["config"]["task"]["model"]["agent_boxes"] = False
    torch.save(state, tmp_path / "no-boxes.pt")
    with pytest.raises(ConfigError, match="does not draw fitted boxes"):
        BoxMotionTask(BoxMotionConfig(world_model=str(tmp_path / "no-boxes.pt")))


def test_box_motion_needs_agent_boxes(world_ckpt):
    from t3fast.models.config import WorldModelConfig
    from t3fast.models.world_model import T3Former

    with pytest.raises(ConfigError, match="'box_motion' moves the fitted boxes 'agent_boxes' draws"):
        WorldModelConfig(forecaster="flow", render_agents=True, box_motion=True)
    model = load_world_model(world_ckpt)
    with pytest.raises(ValueError, match="box_motion moves the fitted boxes agent_boxes draws"):
        T3Former(model.encoder, model.forecaster, model.planner, model.decoder, ego_aligned=True,
                 render_agents=True, box_motion=BoxMotionNet())


def test_a_rotation_turns_counter_clockwise():
    torch.testing.assert_close(rotate(torch.tensor([1.0, 0.0]), torch.tensor(torch.pi / 2)), torch.tensor([0.0, 1.0]),
                               atol=1e-6, rtol=0)


def test_a_window_without_annotated_boxes_gives_no_agents(records):
    from dataclasses import replace

    windows, _ = records
    sample = windows[1]
    hidden = window_record(replace(sample, box_valid=torch.zeros_like(sample.box_valid)))
    none = window_record(replace(sample, boxes=sample.boxes[:, :0], box_valid=sample.box_valid[:, :0],
                                 box_labels=sample.box_labels[:0]))
    for record in (hidden, none):
        assert record["centre"].shape == (0, 2) and record["displacement"].shape == (0, 6, 2)
        assert record["groups"].any()  # the scene is still there
