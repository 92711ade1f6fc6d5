"""A finished run is never replaced by accident; bad counts fail before training starts."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from t3fast.commands.main import main
from t3fast.errors import ConfigError, UsageError
from t3fast.training.run_dir import REPLACED
from t3fast.training.trainer import Trainer
from tests.training.test_trainer import ToyTask, crash_at, toy_config


def run_files(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file()}


def test_second_run_refused_then_resumed_or_overwritten(tmp_path):
    out = tmp_path / "run"
    Trainer(ToyTask(), toy_config(out)).fit()
    finished = run_files(out)
    assert {"last.pt", "best.pt", "metrics.jsonl"} <= finished.keys()

    with pytest.raises(UsageError, match=r"is not empty \(best\.pt, last\.pt, metrics\.jsonl\).*--resume.*--overwrite"):
        Trainer(ToyTask(), toy_config(out))
    assert run_files(out) == finished  # nothing touched

    resumed = Trainer(ToyTask(), toy_config(out, resume=True))
    assert resumed.step == 8

    (out / "notes.txt").write_text("mine")
    Trainer(ToyTask(), toy_config(out, overwrite=True, steps=4)).fit()
    steps = [json.loads(line)["step"] for line in (out / "metrics.jsonl").read_text().splitlines()]
    assert max(steps) == 4 and steps == sorted(steps)  # the old run's events are gone, not appended to
    assert (out / "notes.txt").read_text() == "mine"  # overwrite deletes only what a run writes


class BrokenSetup(ToyTask):
    def __init__(self, part: str) -> None:
        super().__init__()
        self.part = part

    def build_model(self):
        if self.part == "model":
            raise ValueError("init_from='missing.pt': no such checkpoint")
        return super().build_model()

    def train_dataset(self):
        if self.part == "data":
            raise FileNotFoundError("/x.pkl: file not found")
        return super().train_dataset()

    def evaluate(self, model):
        if self.part == "eval":
            raise FileNotFoundError("val info: file not found")
        return super().evaluate(model)


@pytest.mark.parametrize("part", ["model", "data", "eval"])
def test_overwrite_that_fails_before_its_first_checkpoint_keeps_the_old_run(tmp_path, part):
    out = tmp_path / "run"
    Trainer(ToyTask(), toy_config(out)).fit()
    (out / "config.yaml").write_text("old: true\n")
    (out / "tb").mkdir()
    (out / "tb" / "events").write_bytes(b"old events")
    finished = run_files(out)

    with pytest.raises((ValueError, OSError)):
        Trainer(BrokenSetup(part), toy_config(out, overwrite=True, ckpt_every=0)).fit()
    assert run_files(out) == finished  # best.pt, last.pt, metrics.jsonl, config.yaml byte-identical
    assert (out / "tb" / "events").read_bytes() == b"old events"
    assert not (out / REPLACED).exists()


def test_overwrite_replaces_the_old_run_at_its_first_checkpoint(tmp_path):
    out = tmp_path / "run"
    Trainer(ToyTask(), toy_config(out)).fit()
    old = run_files(out)

    trainer = Trainer(ToyTask(), toy_config(out, overwrite=True, steps=6, eval_every=0, ckpt_every=2))
    assert (out / REPLACED / "last.pt").read_bytes() == old["last.pt"]  # set aside, not yet deleted
    assert not (out / "last.pt").exists()
    trainer.fit()
    assert not (out / REPLACED).exists()
    new = run_files(out)
    assert new["last.pt"] != old["last.pt"] and "best.pt" not in new  # the old best.pt went with its run

    # a run that dies after its first checkpoint has replaced the old one for good
    with pytest.raises(RuntimeError, match="simulated crash"):
        Trainer(ToyTask(on_step=crash_at(3)), toy_config(out, overwrite=True, eval_every=0, ckpt_every=2)).fit()
    assert not (out / REPLACED).exists() and (out / "last.pt").read_bytes() != new["last.pt"]


def test_overwrite_after_a_killed_overwrite_keeps_the_finished_run(tmp_path):
    out = tmp_path / "run"
    Trainer(ToyTask(), toy_config(out)).fit()
    finished = run_files(out)
    Trainer(ToyTask(), toy_config(out, overwrite=True))  # killed before its first checkpoint:
    (out / "metrics.jsonl").write_text("{}\n")  # the finished run waits in .replaced-run

    with pytest.raises(FileNotFoundError):
        Trainer(BrokenSetup("eval"), toy_config(out, overwrite=True, ckpt_every=0)).fit()
    assert run_files(out) == finished and not (out / REPLACED).exists()


def test_resume_needs_something_to_resume(tmp_path):
    with pytest.raises(UsageError, match=r"nothing to resume: .*last\.pt does not exist"):
        Trainer(ToyTask(), toy_config(tmp_path / "empty", resume=True))
    assert not (tmp_path / "empty").exists()


def test_contradictory_or_impossible_out_dirs(tmp_path):
    with pytest.raises(UsageError, match="pass one"):
        Trainer(ToyTask(), toy_config(tmp_path / "x", resume=True, overwrite=True))
    (tmp_path / "file").write_text("")
    with pytest.raises(UsageError, match="is a file, not a folder"):
        Trainer(ToyTask(), toy_config(tmp_path / "file"))


@pytest.mark.parametrize(("key", "value"), [("batch_size", 0), ("steps", 0), ("log_every", -1)])
def test_bad_counts_are_config_errors(tmp_path, key, value):
    with pytest.raises(ConfigError, match=f"train.{key} must be at least"):
        toy_config(tmp_path, **{key: value})


def test_cli_refuses_before_building_anything(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "last.pt").write_bytes(b"a finished run")
    base = ["train-ae", "--config", "small", f"train.out_dir={out}"]
    assert main(base) == 2
    assert capsys.readouterr().err.startswith(f"t3fast train-ae: out_dir {out} is not empty (last.pt)")
    assert (out / "last.pt").read_bytes() == b"a finished run"

    empty = tmp_path / "empty"
    assert main(["train-wm", "--config", "small", "--resume", f"train.out_dir={empty}"]) == 2
    assert "nothing to resume" in capsys.readouterr().err

    assert main(["train-ae", "--config", "small", "train.batch_size=0", f"train.out_dir={empty}"]) == 1
    assert capsys.readouterr().err == "t3fast train-ae: train.batch_size must be at least 1, got 0\n"

    assert main(["train-ae", "--config", "nonexistent"]) == 1
    assert "'nonexistent' is neither a preset (small, small-bev, paper) nor a YAML/JSON file" in capsys.readouterr().err

    with pytest.raises(SystemExit):  # argparse: --resume and --overwrite exclude each other
        main(["train-ae", "--resume", "--overwrite"])
    assert "not allowed with argument" in capsys.readouterr().err
