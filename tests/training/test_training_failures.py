"""A run that cannot go on stops with one line naming what is wrong: a loss or weight that is
not finite, a checkpoint that cannot be resumed. No checkpoint ever holds non-finite weights."""

from __future__ import annotations

import os
import pickle
import signal
from pathlib import Path

import pytest
import torch
from torch import nn

import t3fast.training.trainer as trainer_module
from t3fast.errors import CheckpointError, DivergenceError, UsageError
from t3fast.io.checkpoint import load_checkpoint, save_checkpoint
from t3fast.training.run_dir import REPLACED
from t3fast.training.trainer import Trainer
from tests.training.test_run_dir import BrokenSetup, run_files
from tests.training.test_trainer import ToyTask, crash_at, toy_config


def all_finite(path: Path) -> bool:
    state = load_checkpoint(path)
    tensors = list(state["model"].values())
    tensors += [t for s in state.get("optimizer", {}).get("state", {}).values() for t in s.values()]
    return all(bool(torch.isfinite(t).all()) for t in tensors if isinstance(t, torch.Tensor) and t.is_floating_point())


def finished_run(out: Path) -> dict[str, bytes]:
    Trainer(ToyTask(), toy_config(out)).fit()
    return run_files(out)


# ---- overwrite: the replaced run goes only once the new one has trained ---------------------


@pytest.mark.parametrize("fail", ["first step", "second Ctrl-C", "start evaluation"])
def test_overwrite_with_a_start_evaluation_that_fails_before_training_keeps_the_old_run(tmp_path, fail):
    """eval_at_start writes a step-0 best.pt of the untrained model: not a reason to drop the old run."""
    out = tmp_path / "run"
    finished = finished_run(out)

    def hook(n: int) -> None:
        if fail == "second Ctrl-C":
            raise KeyboardInterrupt
        crash_at(1)(n)

    task = BrokenSetup("eval") if fail == "start evaluation" else ToyTask(on_step=hook)
    with pytest.raises((RuntimeError, KeyboardInterrupt, FileNotFoundError)):
        Trainer(task, toy_config(out, overwrite=True, eval_at_start=True)).fit()
    assert run_files(out) == finished and not (out / REPLACED).exists()


def test_overwrite_drops_the_old_run_at_its_first_checkpoint_after_a_step(tmp_path):
    out = tmp_path / "run"
    old = finished_run(out)
    trainer = Trainer(ToyTask(), toy_config(out, overwrite=True, eval_at_start=True, eval_every=1, ckpt_every=0))
    trainer.fit()
    assert not (out / REPLACED).exists() and run_files(out)["best.pt"] != old["best.pt"]


def killed_overwrite(out: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An overwrite with eval_at_start killed in its first step: as if the process died."""
    with monkeypatch.context() as m:
        m.setattr(trainer_module, "restore", lambda out_dir: None)  # a killed process restores nothing
        with pytest.raises(RuntimeError, match="simulated crash"):
            Trainer(ToyTask(on_step=crash_at(1)), toy_config(out, overwrite=True, eval_at_start=True)).fit()
    assert (out / "best.pt").exists() and (out / REPLACED / "last.pt").exists()


def test_overwrite_after_an_overwrite_killed_after_its_start_evaluation_keeps_the_finished_run(tmp_path, monkeypatch):
    out = tmp_path / "run"
    finished = finished_run(out)
    killed_overwrite(out, monkeypatch)

    with pytest.raises(FileNotFoundError):
        Trainer(BrokenSetup("eval"), toy_config(out, overwrite=True, ckpt_every=0)).fit()
    assert run_files(out) == finished and not (out / REPLACED).exists()


def test_resume_after_a_killed_overwrite_names_the_replaced_run(tmp_path, monkeypatch):
    out = tmp_path / "run"
    finished_run(out)
    killed_overwrite(out, monkeypatch)
    with pytest.raises(UsageError) as info:
        Trainer(ToyTask(), toy_config(out, resume=True))
    message = str(info.value)
    assert message.startswith(f"nothing to resume: {out / 'last.pt'} does not exist")
    assert str(out / REPLACED) in message and "move its files back" in message and "\n" not in message


# ---- losses and weights that are not finite ---------------------------------------------------


class NaNData(ToyTask):
    """Every sample holds a NaN: the loss of the first step is NaN."""

    def __init__(self, **kw) -> None:
        super().__init__(**kw)
        self.x[:, 0] = float("nan")


class NaNTermAt(ToyTask):
    """From step ``at`` on, the loss has a named term that is not finite."""

    def __init__(self, at: int, **kw) -> None:
        super().__init__(**kw)
        self.at = at

    def training_step(self, model: nn.Module, batch) -> tuple[torch.Tensor, dict]:
        loss, values = super().training_step(model, batch)
        bad = torch.tensor(float("inf") if self.calls >= self.at else 0.0)
        return loss + bad, {**values, "extra": float(bad)}


def test_nan_in_the_data_stops_at_the_first_step_naming_the_loss(tmp_path):
    with pytest.raises(DivergenceError) as info:
        Trainer(NaNData(), toy_config(tmp_path / "run")).fit()
    assert str(info.value).startswith("train step 1: the loss is not finite (loss=nan, mse=nan)")
    assert not (tmp_path / "run" / "last.pt").exists() and not (tmp_path / "run" / "best.pt").exists()


def test_a_loss_term_that_is_not_finite_is_named_and_nothing_after_it_is_saved(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(DivergenceError, match=r"^train step 5: the loss is not finite \(loss=inf, extra=inf\)"):
        Trainer(NaNTermAt(5), toy_config(out, ckpt_every=2)).fit()
    assert load_checkpoint(out / "last.pt")["step"] == 4 and all_finite(out / "last.pt")


def test_ctrl_c_in_a_step_whose_loss_is_not_finite_saves_nothing(tmp_path):
    def interrupt(n: int) -> None:
        if n == 2:
            os.kill(os.getpid(), signal.SIGINT)

    out = tmp_path / "run"
    with pytest.raises(DivergenceError, match="^train step 2: "):
        Trainer(NaNTermAt(2, on_step=interrupt), toy_config(out, ckpt_every=0, eval_every=0)).fit()
    assert not (out / "last.pt").exists()


@pytest.mark.parametrize("setting", [{"lr": 1e30, "min_lr": 0.0}, {"weight_decay": 1e30}])
def test_rates_far_too_large_stop_the_run_naming_the_step_and_settings(tmp_path, setting):
    out = tmp_path / "run"
    with pytest.raises(DivergenceError) as info:
        Trainer(ToyTask(stochastic=False), toy_config(out, ckpt_every=1, eval_every=1, **setting)).fit()
    message = str(info.value)
    assert message.startswith("train step ") and "is not finite" in message
    assert "train.lr" in message and "train.weight_decay" in message and "\n" not in message
    for name in ("last.pt", "best.pt"):
        assert not (out / name).exists() or all_finite(out / name)


def test_weights_that_stop_being_finite_with_a_finite_loss_stop_the_run(tmp_path):
    """A decay factor of lr x weight_decay = 1e40 overflows the weights in the last step, whose loss was finite."""
    out = tmp_path / "run"
    with pytest.raises(DivergenceError) as info:
        Trainer(ToyTask(), toy_config(out, steps=1, lr=1e20, min_lr=0.0, weight_decay=1e20)).fit()
    assert str(info.value).startswith("train step 1: weight '0.weight' is not finite after the optimiser step (the "
                                      "loss, ")
    assert not (out / "last.pt").exists()


def test_a_model_built_with_values_that_are_not_finite_is_never_saved(tmp_path):
    class NaNBuffer(ToyTask):
        def build_model(self) -> nn.Module:
            model = super().build_model()
            model.register_buffer("stats", torch.tensor([float("nan")]))  # unused: the loss stays finite
            return model

    out = tmp_path / "run"
    with pytest.raises(DivergenceError, match=r"^weight 'stats' is not finite at step 0: best\.pt not written$"):
        Trainer(NaNBuffer(), toy_config(out, eval_at_start=True)).fit()
    assert not (out / "best.pt").exists()


def test_an_overwrite_whose_loss_is_not_finite_keeps_the_old_run(tmp_path):
    out = tmp_path / "run"
    finished = finished_run(out)
    with pytest.raises(DivergenceError):
        Trainer(NaNData(), toy_config(out, overwrite=True)).fit()
    assert run_files(out) == finished


# ---- checkpoints that cannot be resumed --------------------------------------------------------


class WideToy(ToyTask):
    def build_model(self) -> nn.Module:
        return nn.Sequential(nn.Linear(self.dim, 32), nn.Dropout(0.2), nn.Linear(32, 1))


def spoiled_last(out: Path, spoil) -> Path:
    finished_run(out)
    state = load_checkpoint(out / "last.pt")
    spoil(state)
    save_checkpoint(state, out / "last.pt")
    return out / "last.pt"


def resume_error(out: Path, task: ToyTask | None = None, **kw) -> str:
    with pytest.raises(CheckpointError) as info:
        Trainer(task or ToyTask(), toy_config(out, **(kw or {"resume": True})))
    message = str(info.value)
    assert "\n" not in message
    return message


def test_resuming_weights_that_are_not_finite_is_refused(tmp_path):
    last = spoiled_last(tmp_path / "run", lambda s: s["model"]["2.bias"].fill_(float("nan")))
    assert resume_error(tmp_path / "run") == (f"{last}: weight '2.bias' is not finite; a run cannot be resumed "
                                              "from it (resume from an earlier checkpoint or start a new run)")


def test_resuming_optimizer_state_that_is_not_finite_is_refused(tmp_path):
    last = spoiled_last(tmp_path / "run", lambda s: s["optimizer"]["state"][0]["exp_avg"].fill_(float("inf")))
    assert resume_error(tmp_path / "run").startswith(f"{last}: optimizer state 'state.0.exp_avg' is not finite;")


def test_resuming_a_run_of_another_model_size_names_the_weight(tmp_path):
    out = tmp_path / "run"
    finished_run(out)
    assert resume_error(out, WideToy()) == (
        f"{out / 'last.pt'}: weight '0.weight' has shape [16, 4] but this run's model has [32, 4] "
        "(and 2 more wrong weights): it was written by a run with other model settings"
    )


def test_resuming_a_run_with_other_weight_names_names_the_weight(tmp_path):
    class Deeper(ToyTask):
        def build_model(self) -> nn.Module:
            return nn.Sequential(nn.Linear(self.dim, 16), nn.Dropout(0.2), nn.Linear(16, 1), nn.Linear(1, 1))

    out = tmp_path / "run"
    finished_run(out)
    assert resume_error(out, Deeper()) == (
        f"{out / 'last.pt'}: weight '3.weight' is missing (this run's model has it with shape [1, 1]) "
        "(and 1 more wrong weight): it was written by a run with other model settings"
    )


def test_resuming_a_run_with_other_learning_rate_groups_is_refused(tmp_path):
    class Scaled(ToyTask):
        def lr_scales(self) -> dict[str, float]:
            return {"2": 0.5}

    out = tmp_path / "run"
    finished_run(out)
    message = resume_error(out, Scaled())
    assert message.startswith(f"{out / 'last.pt'}: its optimizer state does not fit this run's (")
    assert message.endswith("it was written by a run with other training settings")


def test_resuming_an_exported_checkpoint_is_refused(tmp_path):
    out = tmp_path / "run"
    finished_run(out)
    state = load_checkpoint(out / "last.pt")
    exported = tmp_path / "exported.pt"
    save_checkpoint({"model": state["model"], "config": state["config"], "step": state["step"]}, exported)
    assert resume_error(tmp_path / "new", resume_from=str(exported)) == (
        f"{exported}: an exported (inference) checkpoint, without the optimizer state training needs to go on: "
        "resume from the run's last.pt"
    )


def test_resuming_something_that_is_not_a_training_checkpoint_is_refused(tmp_path):
    plain = tmp_path / "plain.pt"
    save_checkpoint({"weight": torch.zeros(2)}, plain)
    assert resume_error(tmp_path / "new", resume_from=str(plain)) == (
        f"{plain}: not a training checkpoint (it has no 'model', 'optimizer', 'scheduler', 'scaler', 'step', "
        "'best_score', 'rng'): "
        "resume from a run's last.pt"
    )


def test_resuming_a_truncated_last_pt_is_refused(tmp_path):
    out = tmp_path / "run"
    finished_run(out)
    data = (out / "last.pt").read_bytes()
    (out / "last.pt").write_bytes(data[:1000])
    assert resume_error(out).startswith(f"{out / 'last.pt'}: not a readable checkpoint (")


class Payload:
    def __reduce__(self):
        return (print, ("this must not run",))


def test_resuming_a_pickle_payload_is_refused_without_running_it(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "last.pt").write_bytes(pickle.dumps({"model": Payload()}))
    assert resume_error(out).startswith(f"{out / 'last.pt'}: not a readable checkpoint (")
    assert "this must not run" not in capsys.readouterr().out
