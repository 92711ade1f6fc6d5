"""``t3fast eval`` (the world-model table), ``t3fast eval-ae`` (the reconstruction table) and
``t3fast forecast`` (run a model on a sequence)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from t3fast.commands.args import non_negative_int, positive_int
from t3fast.device import default_device
from t3fast.errors import DataFormatError, T3fastError, UsageError
from t3fast.paths import check_name, output_dir, output_file, output_path


def add_evaluation_commands(sub: argparse._SubParsersAction) -> None:
    evaluate = sub.add_parser("eval", help="world-model table: forecasting, planning, speed; baselines and ablations")
    evaluate.add_argument("ckpt", type=Path, nargs="+",
                          help="stage-2 checkpoints or shipped names (wm-small, ...); each row is named after what "
                               "it is (t3former, no_delta, ...)")
    evaluate.add_argument("--split", default="test", choices=["train", "val", "test"])
    evaluate.add_argument("--scenes", type=positive_int, default=10, help="synthetic scenes of the split")
    evaluate.add_argument("--stride", type=positive_int, default=8, help="frames between evaluated windows of a scene")
    evaluate.add_argument("--mask", action="store_true", help="score only voxels in mask_camera")
    evaluate.add_argument("--no-baselines", action="store_true", help="skip Copy&Paste and constant velocity")
    evaluate.add_argument("--out", type=Path, help="write metrics.json and metrics.md here")
    evaluate.set_defaults(func=_eval)

    evaluate = sub.add_parser("eval-ae", help="reconstruction table of a stage-1 checkpoint")
    evaluate.add_argument("ckpt", type=Path, help="checkpoint (best.pt / last.pt)")
    evaluate.add_argument("--split", default="test", choices=["train", "val", "test"])
    evaluate.add_argument("--scenes", type=positive_int, default=10, help="synthetic scenes of the split")
    evaluate.add_argument("--stride", type=positive_int, default=1, help="score every k-th frame")
    evaluate.add_argument("--out", type=Path, help="write the results as JSON here")
    evaluate.set_defaults(func=_eval_ae)

    forecast = sub.add_parser("forecast", help="forecast every window of an Occ3D-layout dataset")
    forecast.add_argument("--data", type=Path, required=True, help="directory holding gts/")
    forecast.add_argument("--info", type=Path, help="info pickle (default: the only *.pkl in --data)")
    forecast.add_argument("--ckpt", type=Path, required=True, help="stage-2 checkpoint or shipped name (wm-small)")
    forecast.add_argument("--out", type=Path, required=True)
    forecast.add_argument("--stride", type=positive_int, default=6, help="frames between forecast windows of a scene")
    forecast.add_argument("--pictures", type=non_negative_int, default=4,
                          help="windows that also get PNG/GIF pictures and a 3D page (HTML)")
    forecast.set_defaults(func=_forecast)


def load_models(paths: list[Path], device: torch.device) -> tuple[dict, dict[str, int | None]]:
    """Stage-2 checkpoints keyed by method name (see :func:`t3fast.evaluation.report.method_name`),
    and the training step each checkpoint was saved at (its ``step``; None where it has none)."""
    from t3fast.evaluation.report import method_name
    from t3fast.io.checkpoint import WORLD_MODEL, read_checkpoint
    from t3fast.pretrained import resolve, world_model_from_checkpoint

    models, steps = {}, {}
    for path in paths:
        state = read_checkpoint(resolve(path), WORLD_MODEL)
        model = world_model_from_checkpoint(state, path).to(device).eval()
        name = method_name(model)
        if name in models:
            raise ValueError(f"{path}: a second {name!r} model; pass one checkpoint per method")
        models[name], steps[name] = model, state.get("step")
    return models, steps


@torch.no_grad()
def forecast_window(model, sample, future_actions: torch.Tensor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The model's forecast of one window (a ``DrivingSample``) from its past frames and poses:
    labels uint8 ``[6, 200, 200, 16]`` and planned positions ``[6, 2]`` (present frame), on
    the CPU. ``future_actions`` ``[1, 6, 2]``: steered along these displacements instead."""
    from t3fast.data.sample import PRESENT, collate_samples

    device = next(model.parameters()).device
    batch = collate_samples([sample]).to(device)
    if future_actions is not None:
        future_actions = future_actions.to(device)
    out = model.forecast(batch.past_occ, batch.ego_poses[:, : PRESENT + 1], future_actions=future_actions)
    return out.labels[0].cpu().numpy(), out.trajectory[0].cpu().numpy()


def _eval(args: argparse.Namespace) -> int:
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.evaluation.report import evaluate_methods, metrics_markdown, write_report

    if args.out:
        output_dir(args.out)
    device = default_device()
    models, steps = load_models(args.ckpt, device)
    dataset = SyntheticDriving(args.split, args.scenes, stride=args.stride)
    if len(dataset) == 0:
        raise UsageError(f"nothing to evaluate: {args.scenes} {args.split} scenes hold no 11-frame window")
    results = evaluate_methods(models, dataset, list(range(len(dataset))), device=device,
                               baselines=not args.no_baselines, use_mask=args.mask, checkpoint_steps=steps)
    title = f"synthetic {args.split}: {args.scenes} scenes, {len(dataset)} windows, device {device}"
    print(metrics_markdown(results, title))
    if args.out:
        for path in write_report(results, args.out, title):
            print(f"wrote {path}")
    return 0


def find_info(data: Path) -> Path:
    """The only info pickle in an Occ3D-layout folder."""
    found = sorted(data.glob("*.pkl"))
    if len(found) != 1:
        raise UsageError(f"found {len(found)} info pickles in {data}; pass --info")
    return found[0]


def _trajectory_json(plan: np.ndarray, where: str) -> str:
    """``{"planned": [[x, y], ...], "seconds": [...]}``; NaN is not JSON, so it is an error."""
    if not np.all(np.isfinite(plan)):
        raise T3fastError(f"{where}: the model planned a non-finite trajectory {plan.tolist()}")
    seconds = [0.5 * (k + 1) for k in range(len(plan))]
    return json.dumps({"planned": plan.tolist(), "seconds": seconds}, allow_nan=False)


def _forecast_paths(out_root: Path, dataset, index: int, pictures: bool) -> dict[str, Path]:
    """Where window ``index``'s forecast goes, each path checked where it will be written: inside
    ``out_root``, with no symbolic link on the way (one left in an earlier output would redirect it)."""
    from t3fast.data.sample import NUM_FUTURE, PRESENT

    scene, start = dataset.index[index]
    token = dataset.infos[scene][start + PRESENT]["token"]
    where = (check_name(scene, "scene name"), check_name(token, "token"))
    paths = {"folder": output_path(out_root, *where), "trajectory": output_path(out_root, *where, "trajectory.json")}
    for k in range(1, NUM_FUTURE + 1):
        output_path(out_root, *where, f"future_{k}")
        paths[f"future_{k}"] = output_path(out_root, *where, f"future_{k}", "labels.npz")
    if pictures:
        for suffix in (".png", ".gif", ".html"):
            paths[suffix] = output_path(out_root, *where, f"forecast{suffix}")
    return paths


def _forecast(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from t3fast.data.occ3d import Occ3DNuScenes
    from t3fast.data.sample import PRESENT
    from t3fast.pretrained import load_world_model
    from t3fast.viz.bev import save_forecast_pictures
    from t3fast.viz.viewer import write_window_viewer

    if not args.data.is_dir():
        raise UsageError(f"--data {args.data} is not a folder")
    out_root = output_dir(args.out)
    info = args.info or find_info(args.data)
    # the info file and the arguments are checked before the model is loaded or run
    dataset = Occ3DNuScenes(args.data, info, stride=args.stride)
    if len(dataset) == 0:
        raise DataFormatError(f"{info}: nothing to forecast: no scene has the 11 frames a window needs")
    for i in range(len(dataset)):  # every output path, before the model runs
        _forecast_paths(out_root, dataset, i, i < args.pictures)
    device = default_device()
    model = load_world_model(args.ckpt, device)
    for i in tqdm(range(len(dataset)), desc="forecast", unit="window"):
        sample = dataset[i]
        labels, plan = forecast_window(model, sample)
        token = dataset.infos[sample.scene][sample.start + PRESENT]["token"]
        paths = _forecast_paths(out_root, dataset, i, i < args.pictures)  # again: the folder may have changed
        trajectory = _trajectory_json(plan, f"scene {sample.scene!r} token {token!r}")  # before writing anything
        for k, frame in enumerate(labels):
            paths[f"future_{k + 1}"].parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(paths[f"future_{k + 1}"], semantics=frame)
        paths["trajectory"].write_text(trajectory)
        if i < args.pictures:
            save_forecast_pictures(paths["folder"] / "forecast", sample.past_occ.numpy(), labels,
                                   sample.future_occ.numpy(), plan, sample.trajectory.numpy())
            write_window_viewer(paths[".html"], sample, labels, plan, f"forecast, {sample.scene} {token}")
    print(f"wrote {len(dataset)} forecasts under {args.out}")
    return 0


def _eval_ae(args: argparse.Namespace) -> int:
    from t3fast.data.synthetic import SyntheticFrames
    from t3fast.device import default_device
    from t3fast.evaluation.reconstruction import evaluate_reconstruction
    from t3fast.io.checkpoint import AUTOENCODER, read_checkpoint
    from t3fast.pretrained import autoencoder_from_checkpoint, checkpoint_config
    from t3fast.training.configs import Stage1Config

    if args.out is not None:
        output_file(args.out, "JSON file")
    state = read_checkpoint(args.ckpt, AUTOENCODER)
    model = autoencoder_from_checkpoint(state, args.ckpt)  # its weights checked against its config
    cfg = checkpoint_config(Stage1Config, state, args.ckpt)
    device = default_device()
    model.to(device)
    frames = SyntheticFrames(args.split, args.scenes, cfg.data.frames_per_scene)
    indices = list(range(0, len(frames), args.stride))
    metrics = evaluate_reconstruction(model, frames, indices, device=device)
    summary = metrics.summary()
    print(f"reconstruction, synthetic {args.split}: {args.scenes} scenes, {len(indices)} frames, "
          f"step {state.get('step')}")
    print(metrics.table())
    print(f"mIoU (classes without ground truth skipped): {100 * metrics.miou(absent='skip'):.2f}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        summary.update(step=state.get("step"), split=args.split, frames=len(indices), latent=cfg.model.latent,
                       latent_size=cfg.model.latent_size)
        args.out.write_text(json.dumps(summary, indent=2))
    return 0
