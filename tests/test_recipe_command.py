"""``t3fast train --recipe``: the stages run in order, each reading the one before, and a rerun
goes on where the last one stopped (skips finished stages, resumes a stopped one)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from t3fast.commands import recipe
from t3fast.commands.main import main
from t3fast.errors import UsageError
from t3fast.io.checkpoint import save_checkpoint


def _run_checkpoint(folder: Path, step: int, steps: int) -> None:
    save_checkpoint({"model": {}, "step": step, "config": {"train": {"steps": steps}}}, folder / "last.pt")


def test_overrides_go_to_their_stage():
    stages = recipe.RECIPES["wm-small"]
    got = recipe.stage_overrides(stages, ["plan:train.steps=2", "box:data.train_scenes=3", "plan:train.lr=0.1"])
    assert got == {"wm": [], "plan": ["train.steps=2", "train.lr=0.1"], "motion": [], "box": ["data.train_scenes=3"]}


@pytest.mark.parametrize("item", ["train.steps=2", "export:x=1", "nope:train.steps=2", "plan:train.steps"])
def test_an_override_without_a_training_stage_is_refused(item):
    with pytest.raises(UsageError, match=rf"override '{item}': expected STAGE:KEY=VALUE with STAGE one of "
                                         r"wm, plan, motion, box$"):
        recipe.stage_overrides(recipe.RECIPES["wm-small"], [item])


def test_a_stage_state_is_read_from_its_folder(tmp_path):
    stage = recipe.Stage("wm", ("train-wm",))
    folder = tmp_path / "wm"
    assert recipe.stage_state(stage, folder) == "new"
    folder.mkdir()
    (folder / "metrics.jsonl").write_text("")
    assert recipe.stage_state(stage, folder) == "restart"  # killed before its first checkpoint
    _run_checkpoint(folder, 3, 10)
    assert recipe.stage_state(stage, folder) == "resume"
    _run_checkpoint(folder, 10, 10)
    assert recipe.stage_state(stage, folder) == "done"
    export = recipe.Stage("export", ("export",), writes=str(tmp_path / "out.pt"))
    assert recipe.stage_state(export, tmp_path) == "new"
    (tmp_path / "out.pt").write_bytes(b"x")
    assert recipe.stage_state(export, tmp_path) == "done"


class IntermixedParser(argparse.ArgumentParser):
    """Flags anywhere among the positional words, as the real sub-commands take them."""

    def parse_args(self, args=None, namespace=None):
        return self.parse_intermixed_args(args, namespace)


class FakeCommands:
    """Stands in for the training and export commands: records each call and writes what the
    real one would leave (a run stopped at ``stop_at`` steps for the stage named ``stop``)."""

    def __init__(self, stop: str | None = None, stop_at: int = 0):
        self.calls: list[list[str]] = []
        self.stop, self.stop_at = stop, stop_at

    def parser(self) -> argparse.ArgumentParser:
        parser = IntermixedParser()
        parser.add_argument("argv", nargs="*")
        parser.add_argument("--config")
        parser.add_argument("--ae")
        parser.add_argument("--wm")
        parser.add_argument("--resume", action="store_true")
        parser.add_argument("--overwrite", action="store_true")
        parser.set_defaults(func=self.run)
        return parser

    def run(self, args: argparse.Namespace) -> int:
        command, *rest = args.argv
        flags = [flag for flag, on in (("--resume", args.resume), ("--overwrite", args.overwrite)) if on]
        self.calls.append([command, *flags])
        if command == "export":
            Path(rest[1]).write_bytes(b"model")
            return 0
        folder = Path(next(a for a in rest if a.startswith("train.out_dir=")).split("=", 1)[1])
        folder.mkdir(parents=True, exist_ok=True)
        if folder.name == self.stop:
            _run_checkpoint(folder, self.stop_at, 10)
            self.stop = None
            return 130
        _run_checkpoint(folder, 10, 10)
        return 0


def test_a_rerun_skips_finished_stages_and_resumes_the_stopped_one(tmp_path, monkeypatch, capsys):
    fake = FakeCommands(stop="motion", stop_at=4)
    monkeypatch.setattr("t3fast.commands.main.build_parser", fake.parser)
    argv = ["--recipe", "wm-small", "--out", str(tmp_path), "plan:train.steps=10"]
    assert recipe._run_recipe(_recipe_args(argv)) == 130
    assert fake.calls == [["train-wm"], ["train-planner"], ["train-motion"]]
    assert "motion stopped (exit 130); run the same command again" in capsys.readouterr().out
    fake.calls.clear()
    assert recipe._run_recipe(_recipe_args(argv)) == 0
    assert fake.calls == [["train-motion", "--resume"], ["train-box-motion"], ["export"]]
    assert (tmp_path / "wm-small.pt").read_bytes() == b"model"
    fake.calls.clear()
    assert recipe._run_recipe(_recipe_args(argv)) == 0
    assert fake.calls == []


def _recipe_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    recipe.add_recipe_command(parser.add_subparsers())
    return parser.parse_args(["train", *argv])


def test_the_command_line_reports_a_bad_override_in_one_line(capsys):
    assert main(["train", "--recipe", "wm-small", "--out", "/nonexistent/x", "wm-train.steps=2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["t3fast train: override 'wm-train.steps=2': expected STAGE:KEY=VALUE with STAGE one of "
                   "wm, plan, motion, box"]


@pytest.mark.parametrize("state", ["new", "resume", "restart"])
def test_every_stage_command_parses_with_the_real_parser(tmp_path, monkeypatch, state):
    """The flags go where argparse takes them (a ``--resume`` after a stage's KEY=VALUE settings
    is refused by the real parser), and the user's overrides come after the stage's own."""
    from t3fast.commands.main import build_parser

    parsed: list[argparse.Namespace] = []

    def parse_only(argv: list[str]) -> argparse.Namespace:
        args = real.parse_args(argv)
        parsed.append(args)
        return argparse.Namespace(func=lambda _: 0)

    real = build_parser()
    monkeypatch.setattr("t3fast.commands.main.build_parser", lambda: argparse.Namespace(parse_args=parse_only))
    monkeypatch.setattr(recipe, "stage_state", lambda stage, folder: state if stage.writes == "run" else "new")
    assert recipe._run_recipe(_recipe_args(["--recipe", "wm-small", "--out", str(tmp_path), "wm:train.steps=3"])) == 0
    assert [a.command for a in parsed] == ["train-wm", "train-planner", "train-motion", "train-box-motion", "export"]
    for args in parsed[:-1]:
        assert (args.resume, args.overwrite) == (state == "resume", state == "restart")
    assert parsed[0].overrides[-2:] == [f"train.out_dir={tmp_path / 'wm'}", "train.steps=3"]
