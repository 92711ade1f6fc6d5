"""What the picture tools share: ``CKPT OUT.png [--split test --scenes 10 --stride 8]``, the
world model loaded and the split's windows made."""

from __future__ import annotations

import argparse
from pathlib import Path

from t3fast.data.synthetic import SyntheticDriving
from t3fast.models.world_model import T3Former
from t3fast.pretrained import load_world_model


def model_windows_out(doc: str) -> tuple[T3Former, SyntheticDriving, Path]:
    """Parse the command line of a tool whose docstring is ``doc``: (the world model in eval
    mode, the synthetic windows to pick from, the picture's path, its folder made)."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("ckpt")
    parser.add_argument("out", type=Path)
    parser.add_argument("--split", default="test")
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--stride", type=int, default=8)
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    return load_world_model(args.ckpt).eval(), SyntheticDriving(args.split, args.scenes, stride=args.stride), args.out
