"""``t3fast export``: a checkpoint slimmed for inference loads to the same model; bad input is refused."""

from __future__ import annotations

import os
import stat

import pytest
import torch

import t3fast
from t3fast.commands.main import main
from t3fast.io.checkpoint import load_checkpoint
from t3fast.pretrained import SHIPPED_DIR

SHIPPED_WM = SHIPPED_DIR / "wm-small.pt"


def test_export_keeps_weights_and_config(tmp_path, capsys):
    out = tmp_path / "wm.pt"
    assert main(["export", str(SHIPPED_WM), str(out), "--dtype", "float32"]) == 0
    assert "wrote" in capsys.readouterr().out
    state = load_checkpoint(out)
    assert set(state) == {"model", "config", "step"}
    assert all(v.dtype == torch.float32 for v in state["model"].values() if v.is_floating_point())
    exported, shipped = t3fast.load_world_model(out), t3fast.load_world_model("wm-small")
    for (k, a), b in zip(exported.state_dict().items(), shipped.state_dict().values()):
        assert torch.equal(a, b), k


def test_export_refuses_what_is_not_a_checkpoint(tmp_path, capsys):
    plain = tmp_path / "plain.pt"
    torch.save({"w": torch.zeros(2)}, plain)
    assert main(["export", str(plain), str(tmp_path / "out.pt")]) == 1
    assert "not a t3fast checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "out.pt").exists()


def test_export_refuses_to_overwrite_its_source_or_a_folder(tmp_path, capsys):
    assert main(["export", str(SHIPPED_WM), str(SHIPPED_WM)]) == 2
    assert "would lose its training state" in capsys.readouterr().err
    assert main(["export", str(SHIPPED_WM), str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err


def test_export_ships_model_options_checked(tmp_path, capsys):
    """``--model key=value`` stores an inference setting instead of the run's, validated."""
    # the shipped model without its box motion network: drawing boxes is then a setting alone
    state = load_checkpoint(SHIPPED_WM)
    state["model"] = {k: v for k, v in state["model"].items() if not k.startswith("box_motion.")}
    state["config"]["task"]["model"]["box_motion"] = False
    source = tmp_path / "no-box-motion.pt"
    torch.save(state, source)
    out = tmp_path / "wm.pt"
    assert t3fast.load_world_model(source).agent_boxes
    assert main(["export", str(source), str(out), "--model", "agent_boxes=false"]) == 0
    exported = t3fast.load_world_model(out)
    assert not exported.agent_boxes and exported.render_agents
    assert load_checkpoint(out)["config"]["task"]["model"]["agent_boxes"] is False
    assert main(["export", str(source), str(tmp_path / "bad.pt"), "--model", "render_agents=false"]) != 0
    assert "'agent_boxes' draws the agents 'render_agents' moves" in capsys.readouterr().err
    assert main(["export", str(SHIPPED_WM), str(tmp_path / "bad.pt"), "--model", "agent_boxes=false"]) != 0
    assert "'box_motion' moves the fitted boxes 'agent_boxes' draws" in capsys.readouterr().err
    assert main(["export", str(SHIPPED_WM), str(tmp_path / "bad.pt"), "--model", "no_such_option=1"]) != 0
    assert "no_such_option" in capsys.readouterr().err
    assert not (tmp_path / "bad.pt").exists()


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    return err.strip()


@pytest.mark.parametrize(("option", "problem"), [
    ("planner=phi_act", "weight 'planner.future_queries' is missing"),
    ("box_motion=false", "weight 'box_motion.view.0.weight' is not part of the model"),
    ("route_modes=1",
     "weight 'planner.head.4.weight' has shape [39, 128] but the config 'task.model' builds [12, 128]"),
    ("route_scene=true", "weight 'planner.scene.0.weight' is missing"),
])
def test_a_setting_the_weights_do_not_fit_keeps_the_shipped_file(tmp_path, capsys, option, problem):
    """The exported file is loaded as users load it before it replaces the output: a setting
    that changes which weights the model has is refused and the model shipped before stays."""
    out = tmp_path / "wm.pt"
    assert main(["export", str(SHIPPED_WM), str(out)]) == 0
    shipped = out.read_bytes()
    capsys.readouterr()
    assert main(["export", str(SHIPPED_WM), str(out), "--model", option]) == 1
    message = _one_line(capsys)
    assert message.startswith(f"t3fast export: {out}: not written, the exported model would not load: {problem}")
    assert out.read_bytes() == shipped and [p.name for p in tmp_path.iterdir()] == ["wm.pt"]
    t3fast.load_world_model(out)


def test_export_refuses_a_link_or_a_special_file_as_output(tmp_path, capsys):
    """Renaming over a FIFO or a device replaces the node with a regular file; a link is refused
    as ``forecast --out`` refuses one."""
    target = tmp_path / "elsewhere.pt"
    target.write_bytes(b"someone else's file")
    link = tmp_path / "link.pt"
    link.symlink_to(target)
    assert main(["export", str(SHIPPED_WM), str(link)]) == 2
    assert _one_line(capsys) == (f"t3fast export: {link} is a symbolic link: not writing through it "
                                 "(remove it or choose another --out)")
    assert link.is_symlink() and target.read_bytes() == b"someone else's file"
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert main(["export", str(SHIPPED_WM), str(fifo)]) == 2
    assert _one_line(capsys) == f"t3fast export: {fifo} is a FIFO, not a regular file: not writing over it"
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere.pt", "fifo", "link.pt"]


def test_float16_export_refuses_weights_beyond_its_range(tmp_path, capsys):
    """70000 becomes inf in float16; the weight and its magnitude are named, float32 keeps it."""
    state = load_checkpoint(SHIPPED_WM)
    state["model"] = {k: v.float() for k, v in state["model"].items()}
    state["model"]["planner.head.4.weight"][3, 7] = -70000.0
    source = tmp_path / "large.pt"
    torch.save(state, source)
    out = tmp_path / "wm.pt"
    assert main(["export", str(source), str(out)]) == 2
    assert _one_line(capsys) == (f"t3fast export: {source}: weight 'planner.head.4.weight' reaches 70000 in "
                                 "magnitude, beyond float16's 65504: export it as float32 (--dtype float32)")
    assert not out.exists()
    assert main(["export", str(source), str(out), "--dtype", "float32"]) == 0
    assert t3fast.load_world_model(out).state_dict()["planner.head.4.weight"][3, 7] == -70000.0
