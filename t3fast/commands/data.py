"""``t3fast data ...``: export synthetic scenes, print statistics, render pictures."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from tqdm import tqdm

from t3fast.commands.args import positive_int
from t3fast.errors import UsageError

#: the longest side of a ``data render`` picture, in pixels (a 6-frame strip at --scale 6 is 7220 wide)
MAX_IMAGE_SIDE = 8192
#: pixels between the tiles of a rendered strip (``t3fast.viz.bev.render_sample``)
TILE_GAP = 4


def add_data_commands(sub: argparse._SubParsersAction) -> None:
    """Register ``data export-synthetic | stats | render`` on the root command's sub-parsers."""
    data = sub.add_parser("data", help="driving data: synthetic towns and Occ3D-nuScenes")
    cmds = data.add_subparsers(dest="data_command", required=True)

    exp = cmds.add_parser("export-synthetic", help="write synthetic scenes in the Occ3D-nuScenes layout")
    exp.add_argument("--out", required=True, help="output directory (gets gts/ and the info pickle)")
    exp.add_argument("--overwrite", action="store_true",
                     help="replace an earlier export of the split in --out (its info file and frames, nothing else)")
    exp.add_argument("--scenes", type=int, default=10, help="number of scenes")
    exp.add_argument("--split", default="train", choices=["train", "val", "test"])
    exp.add_argument("--frames", type=int, default=40, help="2 Hz frames per scene (11 to 1000)")
    exp.set_defaults(func=_export)

    stats = cmds.add_parser("stats", help="class frequencies, height profiles and ego-motion summary of a split")
    _add_source_args(stats)
    stats.add_argument("--occ3d", type=Path,
                       help="profile every labels.npz under this Occ3D folder instead (no info file needed)")
    stats.add_argument("--stride", type=positive_int, default=5, help="window stride for the motion summary")
    stats.set_defaults(func=_stats)

    render = cmds.add_parser("render", help="render a sample's frames as a top-down PNG strip")
    _add_source_args(render)
    render.add_argument("--index", type=int, default=0, help="sample index (windows with stride 1)")
    render.add_argument("--frames", default="0,2,4,6,8,10", help="comma-separated frames of the 11-frame window")
    render.add_argument("--scale", type=int, default=1, help="pixels per voxel")
    render.add_argument("--mask", action="store_true", help="darken voxels outside mask_camera")
    render.add_argument("--out", default="sample.png", help="PNG path")
    render.set_defaults(func=_render)


def _add_source_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--split", default="val", choices=["train", "val", "test"], help="synthetic split")
    p.add_argument("--scenes", type=int, default=8, help="synthetic scenes to use")
    p.add_argument("--frames-per-scene", type=int, default=40, help="2 Hz frames per synthetic scene (11 to 1000)")
    p.add_argument("--root", type=Path, help="read Occ3D-layout data from this directory instead")
    p.add_argument("--info", type=Path, help="info pickle for --root")


def _check_synthetic(scenes: int, frames: int, frames_flag: str) -> None:
    """Refuse scene and frame counts the synthetic generator cannot serve, before any work."""
    from t3fast.data.sample import WINDOW
    from t3fast.data.synthetic.dataset import MAX_FRAMES_PER_SCENE, SPLIT_SIZE

    if not 1 <= scenes <= SPLIT_SIZE:
        raise UsageError(f"--scenes {scenes}: expected 1..{SPLIT_SIZE}")
    if not WINDOW <= frames <= MAX_FRAMES_PER_SCENE:
        raise UsageError(
            f"{frames_flag} {frames}: expected {WINDOW}..{MAX_FRAMES_PER_SCENE} frames per scene "
            f"(a window needs {WINDOW}; a scene is generated whole in memory, about 1.7 MB a frame)"
        )


def _dataset(args: argparse.Namespace, stride: int):
    if args.root is not None:
        from t3fast.data.occ3d import Occ3DNuScenes

        if args.info is None:
            raise UsageError("--root needs --info")
        return Occ3DNuScenes(args.root, args.info, stride=stride)
    from t3fast.data.synthetic.dataset import SyntheticDriving

    _check_synthetic(args.scenes, args.frames_per_scene, "--frames-per-scene")
    return SyntheticDriving(args.split, args.scenes, args.frames_per_scene, stride=stride)


def _export_out(args: argparse.Namespace) -> Path:
    """``--out`` of export-synthetic, checked before any scene is generated: a folder that holds
    an earlier export of the split, or files no export wrote, needs ``--overwrite``; with it the
    earlier export of the split is to be deleted (other files and other splits' exports stay)."""
    from t3fast.data.export import existing_export, foreign_entries
    from t3fast.paths import output_dir

    out = output_dir(args.out)
    found = [p.relative_to(out).as_posix() for p in existing_export(out, args.split)] + foreign_entries(out)
    if found and not args.overwrite:
        shown = ", ".join(found[:5]) + (", ..." if len(found) > 5 else "")
        raise UsageError(f"--out {out} is not empty ({shown}): pass --overwrite to replace the {args.split} export "
                         "there (it deletes only the info file and frames an export wrote)")
    return out


def _export(args: argparse.Namespace) -> int:
    from t3fast.data.export import export_synthetic, remove_export

    out = _export_out(args)

    _check_synthetic(args.scenes, args.frames, "--frames")
    start = time.perf_counter()
    if args.overwrite:
        remove_export(out, args.split)  # only now that every argument has been checked
    info = export_synthetic(args.out, args.split, args.scenes, args.frames)
    print(f"wrote {args.scenes} scenes to {args.out} ({time.perf_counter() - start:.1f} s); info: {info}")
    return 0


def _stats(args: argparse.Namespace) -> int:
    from t3fast.data.stats import format_class_table, format_motion_summary

    if args.occ3d is not None:
        from t3fast.data.occ3d import read_labels

        paths = sorted(Path(args.occ3d).rglob("labels.npz"))
        if not paths:
            raise ValueError(f"--occ3d {args.occ3d}: no labels.npz under it")
        counts, profile = _label_stats(read_labels(p)["semantics"] for p in tqdm(paths, desc="frames", unit="frame"))
        print(f"Occ3D {args.occ3d}: {len(paths)} frames")
        print(format_class_table(counts))
        print(profile)
        return 0
    if args.root is None:
        from t3fast.data.synthetic.dataset import SyntheticScenes

        _check_synthetic(args.scenes, args.frames_per_scene, "--frames-per-scene")
        scenes = SyntheticScenes(args.split, args.scenes, args.frames_per_scene)
        start = time.perf_counter()
        vols = []
        for k in tqdm(range(len(scenes)), desc="scenes", unit="scene"):
            packed = scenes.packed(k)
            vols.extend(packed.frame_occ(t) for t in range(packed.num_frames))
        elapsed = time.perf_counter() - start
        print(f"synthetic {args.split}: {len(scenes)} scenes x {args.frames_per_scene} frames, "
              f"generated in {elapsed:.1f} s ({elapsed / max(len(scenes), 1):.2f} s/scene)")
        counts, profile = _label_stats(vols)
        ds = _dataset(args, args.stride)
        ds.scenes = scenes  # reuse the scenes just generated
    else:
        ds = _dataset(args, args.stride)
        from t3fast.data.occ3d import read_labels

        counts, profile = _label_stats(
            read_labels(ds.label_path(scene, f["token"]))["semantics"]
            for scene, frames in tqdm(ds.infos.items(), desc="scenes", unit="scene")
            for f in frames
        )
    print(format_class_table(counts))
    print(profile)
    print(format_motion_summary(ds[i] for i in range(len(ds))))
    return 0


def _label_stats(volumes) -> tuple:
    """Class counts ``[256]`` and the printed height profile of label volumes, in one pass."""
    import numpy as np

    from t3fast.data import classes as C
    from t3fast.data.stats import class_counts, format_height_profile, height_profile

    counts = np.zeros(256, dtype=np.int64)
    total = np.zeros((C.NUM_CLASSES, C.GRID_SHAPE[2]), dtype=np.int64)
    frames = 0
    for vol in volumes:
        counts += class_counts([vol])
        total += height_profile([vol])[0]
        frames += 1
    return counts, format_height_profile(total, frames)


def _render_frames(text: str, scale: int) -> list[int]:
    """The frames of ``--frames`` (of an 11-frame window), checked with ``--scale`` against
    :data:`MAX_IMAGE_SIDE` before any data is read."""
    from t3fast.data import classes as C
    from t3fast.data.sample import WINDOW

    try:
        frames = [int(f) for f in text.split(",")]
    except ValueError:
        raise UsageError(f"--frames {text!r}: expected comma-separated frame numbers, e.g. 0,2,4") from None
    outside = [f for f in frames if not 0 <= f < WINDOW]
    if outside:
        raise UsageError(f"--frames {text}: frame {outside[0]} is out of range; a window has frames 0..{WINDOW - 1}")
    tile = max(C.GRID_SHAPE[0], C.GRID_SHAPE[1])
    largest = max((MAX_IMAGE_SIDE + TILE_GAP) // len(frames) - TILE_GAP, 0) // tile
    width = len(frames) * tile * scale + TILE_GAP * (len(frames) - 1)
    if scale < 1 or width > MAX_IMAGE_SIDE:
        raise UsageError(
            f"--scale {scale}: expected 1..{largest} for {len(frames)} frames (the picture may be at most "
            f"{MAX_IMAGE_SIDE} pixels wide; each frame is {tile} x --scale pixels)"
            if largest >= 1 else
            f"--frames {text}: {len(frames)} frames do not fit in a picture {MAX_IMAGE_SIDE} pixels wide "
            f"(each frame is {tile} pixels at --scale 1)"
        )
    return frames


def _render(args: argparse.Namespace) -> int:
    from t3fast.viz.bev import save_sample_png

    frames = _render_frames(args.frames, args.scale)
    ds = _dataset(args, 1)
    if not 0 <= args.index < len(ds):
        raise UsageError(f"--index {args.index} is out of range: the data has {len(ds)} windows")
    path = save_sample_png(ds[args.index], args.out, frames, args.scale, args.mask)
    print(f"wrote {path}")
    return 0
