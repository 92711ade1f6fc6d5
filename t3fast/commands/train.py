"""``t3fast train-ae``, ``t3fast train-wm``, ``t3fast train-planner``, ``t3fast train-motion`` and
``t3fast train-box-motion``."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_training_commands(sub: argparse._SubParsersAction) -> None:
    train = sub.add_parser("train-ae", help="pretrain the triplane autoencoder (stage 1)")
    train.add_argument("--config", default="small", help="preset (small, small-bev, paper) or a YAML/JSON file")
    train.add_argument("--data", choices=["synthetic", "occ3d"], help="frame source (overrides the config)")
    _add_run_flags(train)
    train.add_argument("overrides", nargs="*", help="dotted overrides, e.g. train.steps=500 model.channels=16")
    train.set_defaults(func=_train_ae)

    world = sub.add_parser("train-wm", help="train the world model: forecaster, planner, decoder (stage 2)")
    world.add_argument("--config", default="small",
                       help="preset (small, small-no-delta, small-single-scale, small-bev, paper) or a YAML/JSON file")
    world.add_argument("--ae", help="stage-1 checkpoint (overrides autoencoder_ckpt)")
    world.add_argument("--data", choices=["synthetic", "occ3d"], help="window source (overrides the config)")
    _add_run_flags(world)
    world.add_argument("overrides", nargs="*", help="dotted overrides, e.g. train.steps=100 loss.rollout_steps=6")
    world.set_defaults(func=_train_wm)

    for name, part, func in (("train-planner", "route planner", _train_planner),
                             ("train-motion", "motion head", _train_motion),
                             ("train-box-motion", "box motion network", _train_box_motion)):
        one = sub.add_parser(name, help=f"retrain a world model's {part} on its own, on many windows")
        one.add_argument("--config", default="small", help="preset (small) or a YAML/JSON file")
        one.add_argument("--wm", help=f"the world model whose {part} is retrained (overrides world_model)")
        _add_run_flags(one)
        one.add_argument("overrides", nargs="*", help="dotted overrides, e.g. train.steps=1000 data.train_scenes=100")
        one.set_defaults(func=func)


def _add_run_flags(p: argparse.ArgumentParser) -> None:
    runs = p.add_mutually_exclusive_group()
    runs.add_argument("--resume", action="store_true", help="continue the run in OUT_DIR from its last.pt")
    runs.add_argument("--overwrite", action="store_true",
                      help="replace the run already in OUT_DIR (without it a non-empty OUT_DIR is refused)")


def _config(cls, stage: str, name: str, overrides: list[str]):
    """``cls`` from a preset of ``stage`` (:mod:`t3fast.presets`) or a YAML/JSON file, then the
    overrides; the run's out_dir is checked before anything is built."""
    from t3fast.errors import ConfigError
    from t3fast.io.config import config_to_dict, load_config
    from t3fast.presets import names, preset, run_name
    from t3fast.training.run_dir import check_out_dir

    if run_name(name, stage) is not None:
        base = preset(name, stage)
    elif Path(name).is_file():
        base = load_config(cls, name)
    else:
        raise ConfigError(f"--config {name!r} is neither a preset ({', '.join(names(stage))}) nor a YAML/JSON file")
    cfg = load_config(cls, config_to_dict(base), overrides)
    check_out_dir(cfg.train.out_dir, cfg.train.resume, cfg.train.resume_from, cfg.train.overwrite)
    return cfg


def _overrides(args: argparse.Namespace) -> list[str]:
    """The dotted overrides plus those the shared flags stand for."""
    overrides = list(args.overrides)
    if getattr(args, "data", None):
        overrides.append(f"data.source={args.data}")
    if args.resume:
        overrides.append("train.resume=true")
    if args.overwrite:
        overrides.append("train.overwrite=true")
    return overrides


def _fit(task, cfg, parts: tuple[str, ...], name: str) -> int:
    """Train ``task`` with ``cfg.train``; rank 0 saves the resolved config and prints the
    parameter count of each of ``parts`` (submodules of the model) and the final metrics."""
    from t3fast.io.config import save_config
    from t3fast.training.distributed import cleanup, is_main
    from t3fast.training.trainer import Trainer

    trainer = Trainer(task, cfg.train)
    if is_main():
        Path(cfg.train.out_dir).mkdir(parents=True, exist_ok=True)
        save_config(cfg, Path(cfg.train.out_dir) / "config.yaml")
        counts = {part: sum(p.numel() for p in getattr(trainer.module, part).parameters()) for part in parts}
        total = sum(p.numel() for p in trainer.module.parameters())
        print(f"{name}: {total:,} parameters (" + ", ".join(f"{k} {v:,}" for k, v in counts.items()) + ")")
    result = trainer.fit()
    if is_main():
        print(json.dumps(result, indent=2))
    cleanup()
    return 130 if trainer.interrupted else 0


def _train_ae(args: argparse.Namespace) -> int:
    from t3fast.training.autoencoder.task import AutoencoderTask
    from t3fast.training.configs import Stage1Config

    task = AutoencoderTask(_config(Stage1Config, "ae", args.config, _overrides(args)))
    return _fit(task, task.cfg, ("encoder", "decoder"), f"autoencoder {args.config}")


def _train_wm(args: argparse.Namespace) -> int:
    from t3fast.training.configs import Stage2Config
    from t3fast.training.world_model.task import WorldModelTask

    overrides = _overrides(args) + ([f"autoencoder_ckpt={args.ae}"] if args.ae else [])
    task = WorldModelTask(_config(Stage2Config, "wm", args.config, overrides))
    return _fit(task, task.cfg, ("encoder", "forecaster", "planner", "decoder"), f"world model {args.config}")


def _train_planner(args: argparse.Namespace) -> int:
    from t3fast.training.configs import PlannerConfig
    from t3fast.training.planner.task import PlannerTask

    return _retrain_part(args, PlannerTask, PlannerConfig, "plan", ("planner",), "route planner")


def _train_motion(args: argparse.Namespace) -> int:
    from t3fast.training.configs import MotionConfig
    from t3fast.training.motion.task import MotionTask

    return _retrain_part(args, MotionTask, MotionConfig, "motion", ("forecaster",), "motion head")


def _train_box_motion(args: argparse.Namespace) -> int:
    from t3fast.training.box_motion.task import BoxMotionTask
    from t3fast.training.configs import BoxMotionConfig

    return _retrain_part(args, BoxMotionTask, BoxMotionConfig, "box", ("box_motion",), "box motion network")


def _retrain_part(args: argparse.Namespace, task_cls, cfg_cls, stage: str, parts: tuple[str, ...], what: str) -> int:
    """A part of a trained world model (``--wm``) retrained on its own by ``task_cls``."""
    overrides = _overrides(args) + ([f"world_model={args.wm}"] if args.wm else [])
    task = task_cls(_config(cfg_cls, stage, args.config, overrides))
    return _fit(task, task.cfg, parts, f"{what} {args.config}")
