"""``t3fast export``: a training checkpoint slimmed to what inference needs (e.g. to ship it)."""

from __future__ import annotations

import argparse
from pathlib import Path

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


def _export(args: argparse.Namespace) -> int:
    from t3fast.errors import UsageError
    from t3fast.io.checkpoint import export_weights

    if args.out.is_dir():
        raise UsageError(f"{args.out} is a folder; it names the file to write")
    if args.out.resolve() == args.ckpt.resolve():
        raise UsageError(f"{args.out}: writing over the checkpoint being exported would lose its training state")
    size = export_weights(args.ckpt, args.out, DTYPES[args.dtype], args.model)
    print(f"wrote {args.out} ({size / 2**20:.1f} MiB, {args.dtype})")
    return 0
