"""The inference API: shipped names and checkpoint paths load the same model, without training code."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import t3fast
from t3fast.errors import CheckpointError, ConfigError
from t3fast.io.checkpoint import load_checkpoint
from t3fast.pretrained import SHIPPED_DIR, shipped_names


def test_names_resolve_to_the_shipped_checkpoints():
    assert "wm-small" in shipped_names()
    by_name = t3fast.load_world_model("wm-small")
    by_path = t3fast.load_world_model(SHIPPED_DIR / "wm-small.pt")
    assert not by_name.training
    for (k, a), b in zip(by_name.state_dict().items(), by_path.state_dict().values()):
        assert torch.equal(a, b), k
    assert by_name.world_config.ego_aligned and by_name.autoencoder_config.latent == "triplane"


def test_autoencoder_from_a_world_model_has_its_encoder_and_decoder():
    world = t3fast.load_world_model("wm-small")
    ae = t3fast.load_autoencoder("wm-small")
    for part in ("encoder", "decoder"):
        for (k, a), b in zip(getattr(ae, part).state_dict().items(), getattr(world, part).state_dict().values()):
            assert torch.equal(a, b), f"{part}.{k}"
    labels = torch.full((1, 200, 200, 16), 17, dtype=torch.uint8)
    labels[..., 0] = 11
    with torch.no_grad():
        assert ae.reconstruct(labels).shape == (1, 200, 200, 16)


def test_a_stage1_checkpoint_loads_as_autoencoder_not_as_world_model(tmp_path):
    from t3fast.io.checkpoint import save_checkpoint
    from t3fast.io.config import config_to_dict

    world = load_checkpoint(SHIPPED_DIR / "wm-small.pt")
    task = world["config"]["task"]
    stage1 = {"model": {k: v for k, v in world["model"].items() if k.split(".")[0] in ("encoder", "decoder")},
              "config": {"task": {"model": task["autoencoder"], "decoder_backend": "fused"}}, "step": 1}
    save_checkpoint(stage1, tmp_path / "ae.pt")
    assert config_to_dict(t3fast.load_autoencoder(tmp_path / "ae.pt").config) == task["autoencoder"]
    with pytest.raises(CheckpointError, match="stage-1 autoencoder checkpoint.*needs a stage-2"):
        t3fast.load_world_model(tmp_path / "ae.pt")


def test_an_unknown_name_lists_the_shipped_ones():
    with pytest.raises(CheckpointError, match="neither a checkpoint file nor a shipped model.*wm-small"):
        t3fast.load_world_model("wm-huge")


def test_inference_does_not_import_the_training_stack():
    code = ("import sys, t3fast; t3fast.load_world_model('wm-small'); "
            "print(sorted(m for m in sys.modules if m.startswith(('t3fast.training', 't3fast.evaluation'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# ---------------------------------------------------------------- checkpoints that do not fit their config
# a shipped model of the papers' Delta forecaster, whose weight names and shapes the cases below spoil
DELTA_WM = "wm-small-no-delta"


def spoiled(tmp_path, spoil, name="wm.pt"):
    """The shipped Delta-forecaster world model with ``spoil(state)`` applied, saved under ``tmp_path``."""
    from t3fast.io.checkpoint import save_checkpoint

    state = load_checkpoint(SHIPPED_DIR / f"{DELTA_WM}.pt")
    spoil(state)
    save_checkpoint(state, tmp_path / name)
    return tmp_path / name


def _set(section, **values):
    return lambda state: state["config"]["task"][section].update(values)


def _weight(key, value):
    return lambda state: state["model"].__setitem__(key, value)


HEAD = "forecaster.predictors.xy.head.weight"
BAD_CHECKPOINTS = [
    (_weight(HEAD, torch.zeros(8, 32, 1, 1)), CheckpointError,
     f"weight '{HEAD}' has shape [8, 32, 1, 1] but the config 'task.model' builds [8, 16, 1, 1]"),
    (lambda s: s["model"].pop("planner.fc.weight"), CheckpointError,
     "weight 'planner.fc.weight' is missing (the config 'task.model' builds it with shape [50, 50])"),
    (_weight("planner.extra", torch.zeros(3)), CheckpointError,
     "weight 'planner.extra' is not part of the model its config 'task.model' builds"),
    (_weight("planner.fc.weight", "not a tensor"), CheckpointError,
     "weight 'planner.fc.weight' is a str, not a tensor"),
    (_weight("planner.fc.weight", torch.zeros(50, 50, dtype=torch.int64)), CheckpointError,
     "weight 'planner.fc.weight' has dtype torch.int64, not a floating-point one"),
    (lambda s: s["config"]["task"].pop("autoencoder"), ConfigError,
     "its config has no 'task.autoencoder' (the sizes of the model to build)"),
    (lambda s: s["config"]["task"].__setitem__("model", [1, 2]), ConfigError,
     "config 'task.model' must be a mapping of WorldModelConfig fields, got a list"),
    (_set("model", planner_heads=7), ConfigError, "config 'task.model': 'planner_heads' (7) must divide 'd_act' (50)"),
    (_set("model", forecaster_heads=5), ConfigError, "config 'task.model': 'forecaster_heads' (5) must divide every "
     "width of 'forecaster_widths', but not forecaster_widths[0] = 16"),
    (_set("autoencoder", channels=-3), ConfigError,
     "config 'task.autoencoder': 'channels' must be an integer in [1, 65536], got -3"),
    (_set("autoencoder", channels=10**9), ConfigError,
     "config 'task.autoencoder': 'channels' must be an integer in [1, 65536], got 1000000000"),
    (_set("autoencoder", decoder_hidden=[20000, 20000]), CheckpointError,
     "weight 'decoder.mlp.0.weight' has shape [128, 68] but the config 'task.autoencoder' builds [20000, 68] "
     "(and 4 more wrong weights)"),
    (_set("autoencoder", half_res_channels=60000), ConfigError,
     "its config builds a model of 194,404,433,046 parameters, more than the 2,000,000,000 loaded; the largest, "
     "'encoder.half_res.0.body.0.weight' [60000, 60000, 3, 3, 3], is sized by config 'task.autoencoder'"),
    (_set("model", history=0), ConfigError, "config 'task.model': 'history' must be an integer in [2, 65536], got 0"),
]


@pytest.mark.parametrize(("spoil", "error", "message"), BAD_CHECKPOINTS)
def test_a_checkpoint_that_does_not_fit_its_config_is_refused_before_the_model_is_built(
        tmp_path, monkeypatch, spoil, error, message):
    """Named file, key and sizes; nothing is allocated first: the model is only ever built on
    the meta device (a 20000-wide decoder took 1.7 GB and 11 s before its shapes were compared)."""
    from t3fast.models.world_model import T3Former

    path = spoiled(tmp_path, spoil)
    devices = []
    build = T3Former.from_config.__func__

    def recording(cls, *args):
        devices.append(torch.empty(0).device.type)
        return build(cls, *args)

    monkeypatch.setattr(T3Former, "from_config", classmethod(recording))
    with pytest.raises(error) as info:
        t3fast.load_world_model(path)
    assert str(info.value) == f"{path}: {message}"
    assert set(devices) <= {"meta"}


def test_the_autoencoder_of_a_checkpoint_is_checked_too(tmp_path):
    path = spoiled(tmp_path, _set("autoencoder", decoder_hidden=[20000, 20000]))
    with pytest.raises(CheckpointError, match=r"weight 'decoder.mlp.0.weight' has shape \[128, 68\] but the config "
                                              r"'task.autoencoder' builds \[20000, 68\]"):
        t3fast.load_autoencoder(path)
    stage1 = spoiled(tmp_path, lambda s: s.update(
        model={k: v for k, v in s["model"].items() if k.startswith(("encoder.", "decoder."))},
        config={"task": {"model": {**s["config"]["task"]["autoencoder"], "embed_dim": 4}, "decoder_backend": "fused"}},
    ), "ae.pt")
    with pytest.raises(CheckpointError, match=r"ae.pt: weight 'encoder.embed.weight' has shape \[18, 8\] but the "
                                              r"config 'task.model' builds \[18, 4\]"):
        t3fast.load_autoencoder(stage1)


def test_weights_named_as_in_earlier_versions_still_load(tmp_path):
    """Checkpoints from before the identity + residual fusion store the full 1x1 fusion weight."""
    def old_names(state):
        for plane in ("xy", "xz", "yz"):
            residual = state["model"].pop(f"forecaster.fuse_residual.{plane}")
            state["model"][f"forecaster.fuse_weight.{plane}"] = residual + torch.eye(residual.shape[0])

    model, shipped = t3fast.load_world_model(spoiled(tmp_path, old_names)), t3fast.load_world_model(DELTA_WM)
    for (k, a), b in zip(model.state_dict().items(), shipped.state_dict().values()):
        torch.testing.assert_close(a, b, msg=k)


def test_config_values_are_checked_where_configs_are_made():
    from t3fast.models.config import AutoencoderConfig, WorldModelConfig

    with pytest.raises(ConfigError, match=r"'planner_heads' \(7\) must divide 'd_act' \(50\)"):
        WorldModelConfig(planner_heads=7)
    with pytest.raises(ConfigError, match=r"'decoder_hidden\[1\]' must be an integer in \[1, 65536\], got -2"):
        AutoencoderConfig(decoder_hidden=[8, -2])
    with pytest.raises(ConfigError, match=r"'full_res_channels' must be a multiple of 8 .* got 12"):
        AutoencoderConfig(full_res_channels=12)
    with pytest.raises(ConfigError, match=r"'forecaster_layers' must be an integer in \[1, 32\], got 1000"):
        WorldModelConfig(forecaster_layers=1000)


# ---------------------------------------------------------------- weights that are not finite
def _poisoned(tmp_path, key):
    """wm-small with one NaN in weight ``key``."""
    from t3fast.io.checkpoint import save_checkpoint

    state = load_checkpoint(SHIPPED_DIR / "wm-small.pt")
    state["model"][key].view(-1)[3] = float("nan")
    save_checkpoint(state, tmp_path / "wm.pt")
    return tmp_path / "wm.pt"


@pytest.mark.parametrize("key", ["planner.head.0.weight", "box_motion.view.0.weight", "decoder.mlp.0.weight"])
def test_a_weight_that_is_not_finite_is_refused_on_loading(tmp_path, key):
    """A NaN planner or box motion weight said 'cannot convert float NaN to integer' mid-forecast;
    a NaN decoder weight forecast silently wrong."""
    path = _poisoned(tmp_path, key)
    message = f"{path}: weight '{key}' is not finite (1 of its {load_checkpoint(path)['model'][key].numel()} values "
    for load in (t3fast.load_world_model, t3fast.load_autoencoder):
        if load is t3fast.load_autoencoder and not key.startswith("decoder."):
            continue
        with pytest.raises(CheckpointError) as info:
            load(path)
        assert str(info.value) == message + "are NaN or infinite)"


def test_forecast_refuses_a_weight_that_is_not_finite_before_running(tmp_path, capsys):
    from t3fast.commands.main import main
    from t3fast.data.export import export_synthetic

    path = _poisoned(tmp_path, "box_motion.view.0.weight")
    export_synthetic(tmp_path / "occ", "val", 1, 11, progress=False)
    assert main(["forecast", "--data", str(tmp_path / "occ"), "--ckpt", str(path), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == (f"t3fast forecast: {path}: weight 'box_motion.view.0.weight' is not finite "
                                    "(1 of its 1008 values are NaN or infinite)")
