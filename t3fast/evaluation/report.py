"""Scoring every method of the world-model table, and writing it as JSON and markdown."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import torch
from torch.utils.data import Dataset

from t3fast.data.sample import collate_samples
from t3fast.evaluation.world_model import (
    SharedRollout,
    constant_turn_rate_method,
    constant_velocity_method,
    copy_paste_method,
    evaluate_many,
    measure_speed,
    t3former_method,
    track_const_vel_method,
    track_gt_ego_method,
    warp_const_vel_method,
    warp_gt_ego_method,
)
from t3fast.models.world_model import T3Former

# the *_gt_ego rows read the true future poses: references for pure geometry, not forecasters
BASELINES = {"copy_paste": copy_paste_method, "constant_velocity": constant_velocity_method,
             "constant_turn_rate": constant_turn_rate_method, "warp_const_vel": warp_const_vel_method,
             "warp_gt_ego": warp_gt_ego_method, "track_const_vel": track_const_vel_method,
             "track_gt_ego": track_gt_ego_method}


def method_name(model: T3Former) -> str:
    """``"t3former"`` for the full model (the flow forecaster), ``"delta_forecaster"`` for the
    papers' Delta forecaster, else the ablations of the latter it is (``own_frames``: the
    papers' formulation, ``no_delta``, ``single_scale``, ``bev``), read from the sizes it was
    built from."""
    world, latent = model.world_config, model.autoencoder_config.latent
    if getattr(world, "forecaster", "delta") == "flow":
        return "t3former" if latent != "bev" else "bev"
    parts = [name for name, on in (("own_frames", not world.ego_aligned), ("no_delta", not world.predict_delta),
                                   ("single_scale", world.scales == 1), ("bev", latent == "bev")) if on]
    return "_".join(parts) or "delta_forecaster"


def evaluate_methods(
    models: dict[str, T3Former],
    dataset: Dataset,
    indices: list[int],
    device: torch.device | str = "cpu",
    baselines: bool = True,
    use_mask: bool = False,
    progress: bool = True,
    checkpoint_steps: Mapping[str, int | None] | None = None,
) -> dict[str, dict]:
    """The ``metrics.json`` mapping: each model (scores, speed, parameters) and the baselines
    (speed and parameters null), scored in one pass over the windows. Every model plans without
    the route command. The first model, when ego-aligned, also gets ``<name>_gt_ego`` (its
    forecast steered along the true future poses: uses ground-truth ego motion) and, when it
    keeps the observed static world, ``<name>_decoded`` (decoded frames only), both from the same
    forecasting pass, and when its planner reads the route command ``<name>_command`` (planned
    with it: the command is derived from the ego's true future, so that row uses future
    information); the others (the ablations in the demo) get their own row.
    ``checkpoint_steps``: the training step each model's checkpoint was saved at, recorded as
    ``checkpoint_step`` in the rows it gives (None for the baselines)."""
    methods, source = {}, {}
    for position, (name, model) in enumerate(models.items()):
        model.to(device).eval()
        shared = SharedRollout(model, command=False)
        rows = {name: t3former_method(model, shared=shared)}
        if position == 0 and model.ego_aligned:
            rows[f"{name}_gt_ego"] = t3former_method(model, gt_ego=True, shared=shared)
            if model.static_from_present:  # what the latent forecasts on its own, without the observed world
                rows[f"{name}_decoded"] = t3former_method(model, keep_static=False, shared=shared)
        if position == 0 and model.reads_command:
            rows[f"{name}_command"] = t3former_method(model, shared=SharedRollout(model, command=True))
        methods.update(rows)
        source.update(dict.fromkeys(rows, name))
    if baselines:
        methods.update(BASELINES)
    results = evaluate_many(methods, dataset, indices, device=device, use_mask=use_mask, progress=progress,
                            desc="windows")
    timed = collate_samples([dataset[indices[0]]])  # every model is timed on the same window
    steps = checkpoint_steps or {}
    for name, record in results.items():
        speed = measure_speed(models[name], timed) if name in models else {}
        record.update(speed or dict(fps=None, peak_memory_mb=None, params=None))
        record["checkpoint_step"] = steps.get(source.get(name))
    return results


def row_label(name: str, record: dict) -> str:
    """The row's name in the tables. A checkpoint saved at step 0 holds its training run's
    untrained start (``best.pt`` of a run whose validation never beat step 0), and its rows
    say so."""
    if record.get("checkpoint_step") == 0:
        return f"{name} (step 0: untrained, its run never beat its start)"
    return name


def _fmt(value, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def metrics_markdown(results: dict[str, dict], title: str = "") -> str:
    """Two markdown tables: occupancy forecasting (mIoU, IoU and moving-class mIoU per horizon)
    and planning/speed."""
    horizons = ("0s", "1s", "2s", "3s", "avg")
    lines = [f"{title}\n" if title else ""]
    lines.append("| method | " + " | ".join(f"mIoU {h}" for h in horizons) + " | "
                 + " | ".join(f"IoU {h}" for h in horizons) + " | moving mIoU 1s / 2s / 3s | moving mIoU avg |")
    lines.append("|---|" + "---:|" * (2 * len(horizons) + 2))
    for name, r in results.items():
        moving = r.get("miou_moving") or {}  # records written before the column existed lack it
        cells = [_fmt(r["miou"][h]) for h in horizons] + [_fmt(r["iou"][h]) for h in horizons]
        cells += [" / ".join(_fmt(moving.get(h)) for h in ("1s", "2s", "3s")), _fmt(moving.get("avg"))]
        lines.append(f"| {row_label(name, r)} | " + " | ".join(cells) + " |")
    lines += ["", "| method | L2 at 1s / 2s / 3s (m) | L2 avg | mean-L2 1s / 2s / 3s (m) | mean-L2 avg | "
              "collision avg (%) | FPS (batch 1) | peak memory (MB) | parameters |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, r in results.items():
        at = " / ".join(_fmt(r["l2_at"][h]) for h in ("1s", "2s", "3s"))
        mean = " / ".join(_fmt(r["l2_mean"][h]) for h in ("1s", "2s", "3s"))
        coll = None if r["collision"]["avg"] is None else 100 * r["collision"]["avg"]
        params = "-" if r["params"] is None else f"{r['params']:,}"
        lines.append(f"| {row_label(name, r)} | {at} | {_fmt(r['l2_at']['avg'])} | {mean} | "
                     f"{_fmt(r['l2_mean']['avg'])} | {_fmt(coll)} | {_fmt(r['fps'], 1)} | "
                     f"{_fmt(r['peak_memory_mb'], 0)} | {params} |")
    lines += ["", "mIoU/IoU in percent (0s: reconstruction of the present frame; avg: mean of 1-3 s); moving mIoU: "
              "the mIoU over bicycle, bus, car, construction vehicle, motorcycle, pedestrian, trailer, truck. "
              "Rows ending in _gt_ego use the true future ego motion. "
              "Rows ending in _command are given the route command, which is derived from the ego's true future "
              "(its lateral offset 3 s ahead, as nuScenes' gt_ego_fut_cmd); every other row plans without it. "
              "L2 at: distance at the horizon; mean-L2: mean over the steps up to it. "
              "FPS: the whole forecast at batch 1, model.forecast(past labels, past poses): encoding the past "
              "frames, the agents, the forecast, the plan and the 6 frames rendered to labels."]
    return "\n".join(lines).lstrip("\n") + "\n"


def write_report(results: dict[str, dict], out_dir: str | Path, title: str = "") -> tuple[Path, Path]:
    """``out_dir/metrics.json`` and ``out_dir/metrics.md``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(results, indent=2) + "\n")
    (out / "metrics.md").write_text(metrics_markdown(results, title))
    return out / "metrics.json", out / "metrics.md"
