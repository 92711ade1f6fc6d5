"""``t3fast train --recipe NAME``: every training run behind a shipped model, end to end.

A recipe is the list of commands that made a shipped checkpoint, each stage reading the one
before it (``{out}`` and ``{stage}`` name the recipe's folder and a stage's run). Running it
again goes on where it stopped: a stage whose run reached its last step is skipped, one that
stopped part-way (Ctrl-C, a killed machine) resumes from its ``last.pt``, one killed before its
first checkpoint starts again, and the export is skipped once its file exists. Overrides for
one stage go after the recipe as ``STAGE:KEY=VALUE`` (e.g. ``box:train.batch_size=128``).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Stage:
    """One command of a recipe: ``name`` (its folder under the recipe's, and the prefix of its
    overrides), ``argv`` (the ``t3fast`` command line, ``{out}`` / ``{<stage>}`` filled in) and
    ``writes``: ``"run"`` for a training run in ``{out}/<name>``, else the file it writes."""

    name: str
    argv: tuple[str, ...]
    writes: str = "run"


#: the shipped ``wm-small``: stage 2 from the shipped autoencoder for the 800 steps its run trained
#: (the preset's 2,000 were stopped at 769, validation falling; the planner trained alongside is
#: replaced by its own run), then the route planner, the motion head and the box motion network,
#: each trained on its own on the previous run's model, then the export
RECIPES: dict[str, tuple[Stage, ...]] = {
    "wm-small": (
        Stage("wm", ("train-wm", "--config", "small", "--ae", "wm-small", "train.steps=800")),
        Stage("plan", ("train-planner", "--config", "small", "--wm", "{wm}/best.pt")),
        Stage("motion", ("train-motion", "--config", "small", "--wm", "{plan}/best.pt")),
        Stage("box", ("train-box-motion", "--config", "small", "--wm", "{motion}/best.pt")),
        Stage("export", ("export", "{box}/best.pt", "{out}/wm-small.pt"), writes="{out}/wm-small.pt"),
    ),
}


def add_recipe_command(sub: argparse._SubParsersAction) -> None:
    recipe = sub.add_parser("train", help="run every training stage behind a shipped model, resuming where it stopped")
    recipe.add_argument("--recipe", required=True, choices=sorted(RECIPES), help="the shipped model to reproduce")
    recipe.add_argument("--out", type=Path, help="folder of the stages' runs (default runs/recipe-NAME)")
    recipe.add_argument("overrides", nargs="*",
                        help="STAGE:KEY=VALUE overrides of one stage, e.g. plan:train.steps=100")
    recipe.set_defaults(func=_run_recipe)


def stage_overrides(stages: tuple[Stage, ...], overrides: list[str]) -> dict[str, list[str]]:
    """``["plan:train.steps=2"]`` -> ``{"plan": ["train.steps=2"]}``; an unknown stage or a
    missing ``STAGE:`` is a :class:`~t3fast.errors.UsageError` naming the stages."""
    from t3fast.errors import UsageError

    runs = [stage.name for stage in stages if stage.writes == "run"]
    out: dict[str, list[str]] = {name: [] for name in runs}
    for item in overrides:
        name, sep, setting = item.partition(":")
        if not sep or name not in out or "=" not in setting:
            raise UsageError(f"override {item!r}: expected STAGE:KEY=VALUE with STAGE one of {', '.join(runs)}")
        out[name].append(setting)
    return out


def stage_state(stage: Stage, folder: Path) -> str:
    """What a stage's output says about it: ``"done"``, ``"resume"`` (a ``last.pt`` short of
    the run's last step), ``"restart"`` (a folder without a checkpoint) or ``"new"``."""
    from t3fast.io.checkpoint import load_readable_checkpoint

    if stage.writes != "run":
        return "done" if Path(stage.writes).is_file() else "new"
    if not folder.exists():
        return "new"
    last = folder / "last.pt"
    if not last.is_file():
        return "restart"
    state = load_readable_checkpoint(last)
    return "done" if state["step"] >= state["config"]["train"]["steps"] else "resume"


def _run_recipe(args: argparse.Namespace) -> int:
    from t3fast.commands.main import build_parser

    stages = RECIPES[args.recipe]
    out = args.out or Path("runs") / f"recipe-{args.recipe}"
    names = {"out": str(out), **{stage.name: str(out / stage.name) for stage in stages}}
    overrides = stage_overrides(stages, args.overrides)
    stages = tuple(Stage(s.name, tuple(a.format(**names) for a in s.argv), s.writes.format(**names)) for s in stages)
    parser = build_parser()
    for k, stage in enumerate(stages, 1):
        folder = out / stage.name
        state = stage_state(stage, folder)
        print(f"[{k}/{len(stages)}] {stage.name}: {' '.join(stage.argv)} ({state})", flush=True)
        if state == "done":
            continue
        argv = list(stage.argv)
        if stage.writes == "run":  # the flag before the stage's KEY=VALUE settings, which the user's follow
            flag = {"resume": ["--resume"], "restart": ["--overwrite"], "new": []}[state]
            argv[1:1] = flag
            argv += [f"train.out_dir={folder}", *overrides[stage.name]]
        parsed = parser.parse_args(argv)
        code = parsed.func(parsed)
        if code:
            print(f"{stage.name} stopped (exit {code}); run the same command again to go on from there")
            return int(code)
    print(f"{args.recipe}: {stages[-1].writes}")
    return 0
