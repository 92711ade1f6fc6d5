"""Expected errors print one line, ``t3fast <command>: <message>``, and exit non-zero; bugs
keep their traceback; ``--debug`` shows it for expected errors too."""

from __future__ import annotations

import pytest
import torch

from t3fast.commands.main import main
from t3fast.io.checkpoint import save_checkpoint
from t3fast.io.config import config_to_dict
from t3fast.training.configs import Stage1Config

SHIPPED_WM = "t3fast/checkpoints/wm-small.pt"


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err.rstrip("\n")


@pytest.fixture
def stage1_ckpt(tmp_path):
    path = tmp_path / "ae.pt"
    save_checkpoint({"model": {}, "config": {"task": config_to_dict(Stage1Config())}, "step": 0}, path)
    return path


def test_checkpoint_kinds_are_named(tmp_path, stage1_ckpt, capsys):
    assert main(["eval", str(stage1_ckpt)]) == 1
    assert one_line(capsys) == (
        f"t3fast eval: {stage1_ckpt}: this is a stage-1 autoencoder checkpoint (from `t3fast train-ae`); "
        "this command needs a stage-2 world model checkpoint (from `t3fast train-wm`)"
    )
    assert main(["eval-ae", SHIPPED_WM]) == 1
    assert "this is a stage-2 world model checkpoint" in one_line(capsys)

    plain = tmp_path / "state_dict.pt"
    torch.save({"weight": torch.zeros(2)}, plain)
    assert main(["eval", str(plain)]) == 1
    assert "not a t3fast checkpoint" in one_line(capsys)

    text = tmp_path / "notes.pt"
    text.write_text("hello\n")
    assert main(["eval", str(text)]) == 1
    assert one_line(capsys).startswith(f"t3fast eval: {text}: not a readable checkpoint (")

    assert main(["forecast", "--data", str(tmp_path), "--info", str(tmp_path / "x.pkl"), "--ckpt", "x.pt",
                 "--out", str(tmp_path / "o")]) == 1
    assert one_line(capsys) == f"t3fast forecast: {tmp_path / 'x.pkl'}: file not found"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["eval", SHIPPED_WM, "--scenes", "0"], "argument --scenes: must be at least 1, got 0"),
        (["eval", SHIPPED_WM, "--stride", "0"], "argument --stride: must be at least 1, got 0"),
        (["eval-ae", SHIPPED_WM, "--stride", "x"], "argument --stride: expected an integer, got 'x'"),
        (["forecast", "--data", ".", "--ckpt", "c", "--out", "o", "--stride", "-1"],
         "argument --stride: must be at least 1, got -1"),
        (["forecast", "--data", ".", "--ckpt", "c", "--out", "o", "--pictures", "-1"],
         "argument --pictures: must be at least 0, got -1"),
        (["demo", "--scenes", "0"], "argument --scenes: must be at least 1, got 0"),
        (["demo", "--stride", "0"], "argument --stride: must be at least 1, got 0"),
        (["data", "stats", "--stride", "0"], "argument --stride: must be at least 1, got 0"),
    ],
)
def test_bad_numbers_are_refused_by_the_parser(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_out_must_be_a_folder(tmp_path, capsys):
    out = tmp_path / "file.txt"
    out.write_text("")
    assert main(["eval", SHIPPED_WM, "--out", str(out)]) == 2  # before any model runs
    assert one_line(capsys) == f"t3fast eval: --out {out} is a file, not a folder"
    assert main(["forecast", "--data", str(tmp_path), "--ckpt", SHIPPED_WM, "--out", str(out / "sub")]) == 2
    assert one_line(capsys) == f"t3fast forecast: --out {out / 'sub'}: {out} is a file, not a folder"
    assert main(["forecast", "--data", str(out), "--ckpt", SHIPPED_WM, "--out", str(tmp_path)]) == 2
    assert one_line(capsys) == f"t3fast forecast: --data {out} is not a folder"
    assert main(["forecast", "--data", str(tmp_path), "--ckpt", SHIPPED_WM, "--out", str(tmp_path / "o")]) == 2
    assert one_line(capsys) == f"t3fast forecast: found 0 info pickles in {tmp_path}; pass --info"


def test_outputs_are_checked_before_any_work(tmp_path, capsys, monkeypatch, stage1_ckpt):
    import t3fast.commands.evaluate as commands
    from t3fast.data.synthetic.dataset import SyntheticScenes
    from t3fast.io import checkpoint

    def refuse(*args, **kwargs):
        raise AssertionError("did work before checking --out")

    monkeypatch.setattr(commands, "load_models", refuse)
    monkeypatch.setattr(SyntheticScenes, "generate", refuse)
    monkeypatch.setattr(checkpoint, "read_checkpoint", refuse)
    afile = tmp_path / "afile"
    afile.write_text("")
    assert main(["demo", "--out", str(afile)]) == 2
    assert one_line(capsys) == f"t3fast demo: --out {afile} is a file, not a folder"
    assert main(["demo", "--out", str(afile / "sub")]) == 2
    assert one_line(capsys) == f"t3fast demo: --out {afile / 'sub'}: {afile} is a file, not a folder"
    assert main(["view", "--synthetic", "test:0", "--out", str(afile / "v.html")]) == 2
    assert one_line(capsys) == f"t3fast view: --out {afile / 'v.html'}: {afile} is a file, not a folder"
    assert main(["view", "--synthetic", "test:0", "--out", str(tmp_path)]) == 2
    assert one_line(capsys) == f"t3fast view: --out {tmp_path} is a folder; it names the HTML file to write"
    assert main(["eval-ae", str(stage1_ckpt), "--out", str(afile / "deeper" / "m.json")]) == 2
    assert one_line(capsys) == f"t3fast eval-ae: --out {afile / 'deeper' / 'm.json'}: {afile} is a file, not a folder"


def test_debug_shows_the_traceback(tmp_path, capsys):
    text = tmp_path / "notes.pt"
    text.write_text("hello\n")
    for argv in (["--debug", "eval", str(text)], ["eval", str(text), "--debug"]):
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "Traceback" in err and "CheckpointError" in err
        assert err.splitlines()[-1].startswith(f"t3fast eval: {text}: not a readable checkpoint (")


def test_bugs_keep_their_traceback(monkeypatch):
    import t3fast.commands.evaluate as commands

    def broken(*args, **kwargs):
        raise RuntimeError("a bug")

    monkeypatch.setattr(commands, "load_models", broken)
    with pytest.raises(RuntimeError, match="a bug"):
        main(["eval", SHIPPED_WM])


def _spoiled(tmp_path, spoil, name="wm.pt"):
    from t3fast.io.checkpoint import load_checkpoint

    state = load_checkpoint(SHIPPED_WM)
    spoil(state)
    save_checkpoint(state, tmp_path / name)
    return tmp_path / name


HEAD = "forecaster.unet.head.weight"  # the flow forecaster's 1x1 Delta head: 6 steps x 8 channels outputs
WRONG_SHAPE = (lambda s: s["model"].__setitem__(HEAD, torch.zeros(48, 32, 1, 1)),
               f"weight '{HEAD}' has shape [48, 32, 1, 1] but the config 'task.model' builds [48, 16, 1, 1]")
NO_AUTOENCODER = (lambda s: s["config"]["task"].pop("autoencoder"),
                  "its config has no 'task.autoencoder' (the sizes of the model to build)")
BAD_HEADS = (lambda s: s["config"]["task"]["model"].update(planner_heads=7),
             "config 'task.model': 'planner_heads' (7) must divide 'd_act' (50)")


@pytest.mark.parametrize(
    ("spoil", "message"),
    [
        WRONG_SHAPE,
        (lambda s: s["model"].pop("planner.head.0.weight"),
         "weight 'planner.head.0.weight' is missing (the config 'task.model' builds it with shape [128, 11])"),
        (lambda s: s["model"].__setitem__("planner.extra", torch.zeros(2)),
         "weight 'planner.extra' is not part of the model its config 'task.model' builds"),
        NO_AUTOENCODER,
        (lambda s: s["config"]["task"].__setitem__("model", [1, 2]),
         "config 'task.model' must be a mapping of WorldModelConfig fields, got a list"),
        BAD_HEADS,
        (lambda s: s["config"]["task"]["autoencoder"].update(channels=-8),
         "config 'task.autoencoder': 'channels' must be an integer in [1, 65536], got -8"),
        (lambda s: s["model"].__setitem__("planner.head.0.weight", "a string"),
         "weight 'planner.head.0.weight' is a str, not a tensor"),
    ],
)
def test_a_checkpoint_that_does_not_fit_its_config_is_one_line_in_eval(tmp_path, capsys, spoil, message):
    path = _spoiled(tmp_path, spoil)
    assert main(["eval", str(path), "--scenes", "1"]) == 1
    assert one_line(capsys) == f"t3fast eval: {path}: {message}"


def test_a_checkpoint_that_does_not_fit_its_config_is_one_line_in_eval_ae_and_export(tmp_path, capsys):
    def stage1(extra):
        def spoil(state):
            task = state["config"]["task"]
            state["model"] = {k: v for k, v in state["model"].items() if k.startswith(("encoder.", "decoder."))}
            state["config"]["task"] = {**config_to_dict(Stage1Config()), "model": task["autoencoder"]}
            extra(state)
        return spoil

    path = _spoiled(tmp_path, stage1(lambda s: s["model"].__setitem__("decoder.mlp.0.weight", torch.zeros(128, 9))))
    assert main(["eval-ae", str(path), "--scenes", "1"]) == 1
    assert one_line(capsys) == (f"t3fast eval-ae: {path}: weight 'decoder.mlp.0.weight' has shape [128, 9] but "
                                "the config 'task.model' builds [128, 68]")
    path = _spoiled(tmp_path, stage1(lambda s: s["config"]["task"]["model"].update(decoder_hidden=[20000, 20000])))
    assert main(["eval-ae", str(path), "--scenes", "1"]) == 1
    assert one_line(capsys) == (f"t3fast eval-ae: {path}: weight 'decoder.mlp.0.weight' has shape [128, 68] but "
                                "the config 'task.model' builds [20000, 68] (and 4 more wrong weights)")
    path = _spoiled(tmp_path, stage1(lambda s: s["config"]["task"].__setitem__("model", "small")))
    assert main(["eval-ae", str(path), "--scenes", "1"]) == 1
    assert one_line(capsys) == (f"t3fast eval-ae: {path}: config 'task.model' must be a mapping of "
                                "AutoencoderConfig fields, got a str")

    path = _spoiled(tmp_path, lambda s: s["model"].__setitem__("planner.head.0.weight", "a string"))
    assert main(["export", str(path), str(tmp_path / "out.pt")]) == 1
    assert one_line(capsys) == f"t3fast export: {path}: weight 'planner.head.0.weight' is a str, not a tensor"
    assert not (tmp_path / "out.pt").exists()


@pytest.mark.parametrize("spoil_message", [WRONG_SHAPE, NO_AUTOENCODER, BAD_HEADS])
def test_a_checkpoint_that_does_not_fit_its_config_is_one_line_in_forecast(tmp_path, capsys, spoil_message):
    from t3fast.data.export import export_synthetic

    spoil, message = spoil_message
    root = tmp_path / "occ3d"
    info = export_synthetic(root, "val", 1, 11, progress=False)
    path = _spoiled(tmp_path, spoil)
    out = tmp_path / "out"
    assert main(["forecast", "--data", str(root), "--info", str(info), "--ckpt", str(path), "--out", str(out)]) == 1
    assert one_line(capsys) == f"t3fast forecast: {path}: {message}"
    assert not list(out.rglob("*.npz"))


def test_ctrl_c_before_training_is_one_line(tmp_path, capsys, monkeypatch):
    from t3fast.training.planner.plan_cache import PlanCache

    def interrupted(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(PlanCache, "build", interrupted)
    argv = ["train-planner", "--config", "plan-small", "train.steps=1", "data.train_scenes=1", "data.val_scenes=1",
            f"data.cache_dir={tmp_path / 'cache'}", f"train.out_dir={tmp_path / 'run'}"]
    assert main(argv) == 130
    assert one_line(capsys) == "t3fast train-planner: interrupted"
    assert main([*argv, "--debug"]) == 130
    err = capsys.readouterr().err
    assert "Traceback" in err and "KeyboardInterrupt" in err and err.endswith("t3fast train-planner: interrupted\n")


PLANNER_RUN = ["train-planner", "--config", "plan-small", "train.steps=2", "data.train_scenes=1", "data.val_scenes=1",
               "train.batch_size=4"]


def last_line(capsys) -> str:
    """The error line after a training command's progress bars."""
    err = capsys.readouterr().err
    assert err.endswith("\n") and "Traceback" not in err, err
    return err.splitlines()[-1]


def test_training_that_diverges_is_one_line(tmp_path, capsys):
    run = [*PLANNER_RUN, f"data.cache_dir={tmp_path / 'cache'}", f"train.out_dir={tmp_path / 'run'}"]
    assert main([*run, "train.lr=1e30", "train.min_lr=0"]) == 1
    message = last_line(capsys)
    assert message.startswith("t3fast train-planner: train step ") and "is not finite" in message
    assert not (tmp_path / "run" / "last.pt").exists()


def test_resuming_a_run_of_another_size_is_one_line(tmp_path, capsys):
    run = [*PLANNER_RUN, f"data.cache_dir={tmp_path / 'cache'}", f"train.out_dir={tmp_path / 'run'}"]
    assert main(run) == 0
    capsys.readouterr()
    assert main([*run, "modes=1", "--resume"]) == 1
    message = last_line(capsys)
    assert message.startswith(f"t3fast train-planner: {tmp_path / 'run' / 'last.pt'}: weight ")
    assert message.endswith("it was written by a run with other model settings")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_on_a_machine_without_it_is_one_line(tmp_path, capsys):
    argv = [*PLANNER_RUN, "train.device=cuda", f"data.cache_dir={tmp_path / 'cache'}",
            f"train.out_dir={tmp_path / 'run'}"]
    assert main(argv) == 1
    assert one_line(capsys) == ("t3fast train-planner: train.device is 'cuda' but CUDA is not available here: "
                                "use train.device=cpu (or auto)")
