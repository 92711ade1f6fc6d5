"""``t3fast export``: a training checkpoint slimmed to what inference needs (e.g. to ship it)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32}


def add_export_command(sub: argparse._SubParsersAction) -> None:
    export = sub.add_parser("export", help="keep only a checkpoint's weights and config, e.g. to ship a model")
    export.add_argument("ckpt", type=Path, help="stage-1 or stage-2 checkpoint (best.pt / last.pt)")
    export.add_argument("out", type=Path, help="the file to write (loads with t3fast.load_world_model / eval / demo)")
    export.add_argument("--dtype", choices=sorted(DTYPES), default="float16",
                        help="dtype of the stored weights; loading casts back to float32 (default float16)")
    export.add_argument("--model", action="append", default=[], metavar="KEY=VALUE",
                        help="a world-model setting to ship instead of the run's (inference options such as "
                             "agent_boxes=true; the weights must still fit); repeatable")
    export.set_defaults(func=_export)


def model_options(options: list[str]) -> Callable[[dict[str, Any], str | None], dict[str, Any]]:
    """A config edit for :func:`~t3fast.pretrained.export_weights`: a world model's config
    with the ``"key=value"`` settings of its model section replaced, validated by
    :class:`~t3fast.models.config.WorldModelConfig` (:class:`~t3fast.errors.ConfigError` for an
    invalid one, or for an autoencoder checkpoint)."""
    from t3fast.errors import ConfigError
    from t3fast.io.checkpoint import WORLD_MODEL
    from t3fast.io.config import config_to_dict, load_config
    from t3fast.models.config import WorldModelConfig

    def edit(config: dict[str, Any], kind: str | None) -> dict[str, Any]:
        if kind != WORLD_MODEL:
            raise ConfigError(f"model options {options} are world-model settings; this is an autoencoder checkpoint")
        task = dict(config["task"])
        task["model"] = config_to_dict(load_config(WorldModelConfig, task.get("model", {}), options))
        return {**config, "task": task}

    return edit


def writable_file(path: Path) -> Path:
    """``path`` as a file a command writes whole, checked before the work: not a symbolic link
    (:func:`~t3fast.paths.output_path`: a link would send the write elsewhere) and, when
    something is there, a regular file (:func:`~t3fast.io.checkpoint.check_replaceable`).
    Raises :class:`~t3fast.errors.UsageError`."""
    from t3fast.io.checkpoint import check_replaceable
    from t3fast.paths import output_path

    output_path(path.parent, path.name)
    check_replaceable(path)
    return path


def _export(args: argparse.Namespace) -> int:
    from t3fast.errors import UsageError
    from t3fast.pretrained import export_weights

    if args.out.is_dir():
        raise UsageError(f"{args.out} is a folder; it names the file to write")
    writable_file(args.out)
    if args.out.resolve() == args.ckpt.resolve():
        raise UsageError(f"{args.out}: writing over the checkpoint being exported would lose its training state")
    size = export_weights(args.ckpt, args.out, DTYPES[args.dtype], model_options(args.model) if args.model else None)
    print(f"wrote {args.out} ({size / 2**20:.1f} MiB, {args.dtype})")
    return 0
