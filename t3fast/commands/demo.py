"""``t3fast demo``: the world model on held-out synthetic scenes, end to end.

Loads the world model shipped in ``t3fast/checkpoints`` (T3Former, trained on synthetic data by
the commands in the README; with ``--ablations`` also the shipped ablations) or the ones in
``--ckpt-dir``, evaluates them and the baselines on held-out synthetic test scenes, and writes
into the
output folder ``metrics.json``, ``metrics.md`` and, for a few test windows, pictures of
past / predicted / ground-truth BEV frames with planned vs true trajectory (PNG and GIF) and
in 3D (HTML), for the first one also the forecast steered to a stop, and ``index.html`` with
the tables, the per-horizon curves, the pictures and links to the 3D pages: what to open first.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from t3fast.commands.args import non_negative_int, positive_int
from t3fast.errors import UsageError
from t3fast.paths import output_dir
from t3fast.presets import shipped_world_models
from t3fast.pretrained import SHIPPED_DIR


def add_demo_command(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser("demo", help="evaluate the shipped world models on held-out synthetic scenes, with pictures")
    demo.add_argument("--out", type=Path, default=Path("demo"), help="output folder")
    demo.add_argument("--ckpt-dir", type=Path, default=SHIPPED_DIR,
                      help="folder with wm-small*.pt checkpoints (default: the shipped ones)")
    demo.add_argument("--scenes", type=positive_int, default=10, help="held-out synthetic test scenes")
    demo.add_argument("--stride", type=positive_int, default=8, help="frames between evaluated windows of a scene")
    demo.add_argument("--pictures", type=non_negative_int, default=3, help="test windows drawn as PNG and GIF")
    # the four ablations take three quarters of the demo's time on a 2-core CPU
    demo.add_argument("--ablations", action="store_true",
                      help="also the shipped ablations (wm-small-*.pt), each a row of the same table")
    demo.set_defaults(func=_demo)


def checkpoint_paths(folder: Path, ablations: bool = True) -> list[Path]:
    """The demo's checkpoints in ``folder`` (the world-model presets found there, see
    :func:`t3fast.presets.shipped_world_models`): ``wm-small.pt`` first, then (``ablations``)
    the ablations."""
    paths = shipped_world_models(folder)
    if not paths or paths[0].name != "wm-small.pt":
        raise UsageError(f"{folder / 'wm-small.pt'} not found (train it with `t3fast train-wm --config small`)")
    return paths if ablations else paths[:1]


def save_pictures(model, dataset, indices: list[int], out: Path) -> list[Path]:
    """PNG + GIF and a 3D page (HTML) of the forecasts of ``indices``."""
    from t3fast.commands.evaluate import forecast_window
    from t3fast.data.sample import NUM_FUTURE
    from t3fast.viz.bev import save_forecast_pictures
    from t3fast.viz.viewer import write_window_viewer

    written = []
    for n, i in enumerate(indices):
        sample = dataset[i]
        labels, plan = forecast_window(model, sample)
        name = f"{sample.scene}-t{sample.start:02d}"
        past, truth, true_plan = sample.past_occ.numpy(), sample.future_occ.numpy(), sample.trajectory.numpy()
        written += save_forecast_pictures(out / name, past, labels, truth, plan, true_plan)
        written.append(write_window_viewer(out / f"{name}.html", sample, labels, plan, f"T3Former forecast, {name}"))
        if n == 0 and model.ego_aligned:  # steered: the same window if the ego stopped now
            stop = torch.zeros(1, NUM_FUTURE, 2, device=next(model.parameters()).device)
            steered, stopped = forecast_window(model, sample, future_actions=stop)
            written += save_forecast_pictures(out / f"{name}-steered-stop", past, steered, truth, stopped, true_plan)
    return written


def _demo(args: argparse.Namespace) -> int:
    from t3fast.commands.evaluate import load_models
    from t3fast.data.synthetic import SyntheticDriving
    from t3fast.device import default_device
    from t3fast.evaluation.report import evaluate_methods, metrics_markdown, write_report
    from t3fast.viz.index_page import write_index

    output_dir(args.out)  # before any model runs
    start = time.perf_counter()
    device = default_device()
    models, steps = load_models(checkpoint_paths(args.ckpt_dir, args.ablations), device)
    print(f"models: {', '.join(models)} ({device})")
    dataset = SyntheticDriving("test", args.scenes, stride=args.stride)
    results = evaluate_methods(models, dataset, list(range(len(dataset))), device=device, checkpoint_steps=steps)
    title = f"synthetic test split: {args.scenes} held-out scenes, {len(dataset)} windows, device {device}"
    paths = list(write_report(results, args.out, title))
    per_scene = len(dataset) // args.scenes
    picks = [k * per_scene for k in range(min(args.pictures, args.scenes))]
    paths += save_pictures(next(iter(models.values())), dataset, picks, args.out / "pictures")  # wm-small's
    views = [p for p in paths if p.suffix == ".html"]
    pictures = [p for p in paths if p.suffix in (".png", ".gif")]
    index = write_index(args.out, results, title, pictures, views)
    print(metrics_markdown(results, title))
    for path in paths:
        print(f"wrote {path}")
    print(f"demo finished in {time.perf_counter() - start:.0f} s; open {index.resolve()}")
    return 0
