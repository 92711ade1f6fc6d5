"""``t3fast view``: an 11-frame window in 3D, as one self-contained HTML page; with ``--ckpt``
the world model's forecast of it next to the ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from t3fast.commands.args import non_negative_int
from t3fast.commands.export import writable_file
from t3fast.data.sample import WINDOW
from t3fast.errors import UsageError
from t3fast.paths import output_file


def add_view_command(sub: argparse._SubParsersAction) -> None:
    view = sub.add_parser("view", help="a window of a dataset in 3D (HTML), optionally with a model's forecast")
    source = view.add_mutually_exclusive_group(required=True)
    source.add_argument("--synthetic", metavar="SPLIT:SCENE", help="a synthetic scene, e.g. test:0")
    source.add_argument("--data", type=Path, help="an Occ3D-layout folder (holding gts/)")
    view.add_argument("--info", type=Path, help="info pickle for --data (default: the only *.pkl in it)")
    view.add_argument("--scene", help="scene name in --data (default: the first)")
    view.add_argument("--start", type=non_negative_int, default=0, help="first frame of the 11-frame window")
    view.add_argument("--ckpt", help="world model (shipped name such as wm-small, or a checkpoint): show its forecast")
    view.add_argument("--out", type=Path, default=Path("view.html"), help="HTML file to write")
    view.set_defaults(func=_view)


def _window(args: argparse.Namespace):
    """The window the arguments name, and a title for it."""
    if args.synthetic is not None:
        from t3fast.data.synthetic.dataset import SyntheticScenes

        split, _, index = args.synthetic.partition(":")
        if split not in ("train", "val", "test") or not index.isdigit():
            raise UsageError(f"--synthetic {args.synthetic!r}: expected SPLIT:SCENE, e.g. test:0")
        scene = SyntheticScenes(split, int(index) + 1).packed(int(index))
        last = scene.num_frames - WINDOW
        if args.start > last:
            raise UsageError(f"--start {args.start}: the scene's 11-frame windows start at 0..{last}")
        return scene.window(args.start), f"synthetic {split} scene {index}"
    from t3fast.commands.evaluate import find_info
    from t3fast.data.occ3d import Occ3DNuScenes

    if not args.data.is_dir():
        raise UsageError(f"--data {args.data} is not a folder")
    info = args.info or find_info(args.data)
    dataset = Occ3DNuScenes(args.data, info, scenes=None if args.scene is None else [args.scene])
    starts = [k for k, (scene, start) in enumerate(dataset.index) if start == args.start]
    if not starts:
        raise UsageError(f"--start {args.start}: no 11-frame window of {args.scene or 'the first scene'} starts there")
    sample = dataset[starts[0]]
    return sample, f"{args.data.name} {sample.scene}"


def _view(args: argparse.Namespace) -> int:
    from t3fast.viz.viewer import write_window_viewer

    writable_file(output_file(args.out, "HTML file"))
    sample, title = _window(args)
    title = f"{title}, frames {sample.start}-{sample.start + WINDOW - 1}"
    predicted = plan = None
    if args.ckpt is not None:
        from t3fast.commands.evaluate import forecast_window
        from t3fast.device import default_device
        from t3fast.pretrained import load_world_model

        predicted, plan = forecast_window(load_world_model(args.ckpt, default_device()), sample)
        title = f"{args.ckpt} forecast, {title}"
    path = write_window_viewer(args.out, sample, predicted, plan, title)
    print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB); open it in a browser")
    return 0
