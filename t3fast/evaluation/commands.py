"""``t3fast eval`` (the world-model table) and ``t3fast forecast`` (run a model on a sequence)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from t3fast.training.distributed import default_device


def add_evaluation_commands(sub: argparse._SubParsersAction) -> None:
    evaluate = sub.add_parser("eval", help="world-model table: forecasting, planning, speed; baselines and ablations")
    evaluate.add_argument("ckpt", type=Path, nargs="+",
                          help="stage-2 checkpoints; each row is named after what it is (t3former, no_delta, ...)")
    evaluate.add_argument("--split", default="test", choices=["train", "val", "test"])
    evaluate.add_argument("--scenes", type=int, default=10, help="synthetic scenes of the split")
    evaluate.add_argument("--stride", type=int, default=8, help="frames between evaluated windows of a scene")
    evaluate.add_argument("--mask", action="store_true", help="score only voxels in mask_camera")
    evaluate.add_argument("--no-baselines", action="store_true", help="skip Copy&Paste and constant velocity")
    evaluate.add_argument("--out", type=Path, help="write metrics.json and metrics.md here")
    evaluate.set_defaults(func=_eval)

    forecast = sub.add_parser("forecast", help="forecast every window of an Occ3D-layout dataset")
    forecast.add_argument("--data", type=Path, required=True, help="directory holding gts/")
    forecast.add_argument("--info", type=Path, help="info pickle (default: the only *.pkl in --data)")
    forecast.add_argument("--ckpt", type=Path, required=True, help="stage-2 checkpoint")
    forecast.add_argument("--out", type=Path, required=True)
    forecast.add_argument("--stride", type=int, default=6, help="frames between forecast windows of a scene")
    forecast.add_argument("--pictures", type=int, default=4, help="windows that also get PNG/GIF pictures")
    forecast.set_defaults(func=_forecast)


def load_models(paths: list[Path], device: torch.device) -> dict:
    """Stage-2 checkpoints keyed by method name (see :func:`t3fast.evaluation.report.method_name`)."""
    from t3fast.evaluation.report import method_name
    from t3fast.training.world_model import load_world_model

    models = {}
    for path in paths:
        model, cfg = load_world_model(path, device)
        name = method_name(cfg.model.predict_delta, cfg.model.scales, cfg.autoencoder.latent)
        if name in models:
            raise ValueError(f"{path}: a second {name!r} model; pass one checkpoint per method")
        models[name] = model
    return models


def _eval(args: argparse.Namespace) -> int:
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.evaluation.report import evaluate_methods, metrics_markdown, write_report

    device = default_device()
    models = load_models(args.ckpt, device)
    dataset = SyntheticDriving(args.split, args.scenes, stride=args.stride)
    results = evaluate_methods(models, dataset, list(range(len(dataset))), device=device,
                               baselines=not args.no_baselines, use_mask=args.mask)
    title = f"synthetic {args.split}: {args.scenes} scenes, {len(dataset)} windows, device {device}"
    print(metrics_markdown(results, title))
    if args.out:
        for path in write_report(results, args.out, title):
            print(f"wrote {path}")
    return 0


def _find_info(data: Path) -> Path:
    found = sorted(data.glob("*.pkl"))
    if len(found) != 1:
        raise SystemExit(f"t3fast forecast: found {len(found)} info pickles in {data}; pass --info")
    return found[0]


@torch.no_grad()
def _forecast(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from t3fast.data.occ3d import Occ3DNuScenes
    from t3fast.data.sample import PRESENT, collate_samples
    from t3fast.training.world_model import load_world_model
    from t3fast.viz import save_forecast_pictures

    device = default_device()
    model, _ = load_world_model(args.ckpt, device)
    dataset = Occ3DNuScenes(args.data, args.info or _find_info(args.data), stride=args.stride)
    for i in tqdm(range(len(dataset)), desc="forecast", unit="window"):
        sample = dataset[i]
        batch = collate_samples([sample]).to(device)
        out = model.forecast(batch.past_occ, batch.past_actions)
        token = dataset.infos[sample.scene][sample.start + PRESENT]["token"]
        folder = args.out / sample.scene / token
        labels = out.labels[0].cpu().numpy()
        for k, frame in enumerate(labels):
            (folder / f"future_{k + 1}").mkdir(parents=True, exist_ok=True)
            np.savez_compressed(folder / f"future_{k + 1}" / "labels.npz", semantics=frame)
        plan = out.trajectory[0].cpu().numpy()
        seconds = [0.5 * (k + 1) for k in range(len(plan))]
        (folder / "trajectory.json").write_text(json.dumps({"planned": plan.tolist(), "seconds": seconds}))
        if i < args.pictures:
            save_forecast_pictures(folder / "forecast", sample.past_occ.numpy(), labels, sample.future_occ.numpy(),
                                   plan, sample.trajectory.numpy())
    print(f"wrote {len(dataset)} forecasts under {args.out}")
    return 0
