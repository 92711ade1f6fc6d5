"""``t3fast export``: a checkpoint slimmed for inference loads to the same model; bad input is refused."""

from __future__ import annotations

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
