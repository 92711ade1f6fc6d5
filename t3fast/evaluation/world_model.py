"""The world-model evaluation protocol: occupancy forecasting and planning, per method.

A *method* maps a :class:`~t3fast.data.sample.DrivingBatch` to a :class:`MethodOutput`
(future labels and/or planned displacements, and for learned models the reconstruction of
the present frame, the "0 s" column). :func:`evaluate_forecasts` scores a method on a set of
windows and returns the ``metrics.json`` record of that method (percent for occupancy, metres
for L2, a rate for collisions; ``None`` where a metric does not apply)::

    {"miou": {"0s", "1s", "2s", "3s", "avg"}, "miou_moving": {...}, "iou": {...},
     "l2_at": {"1s", "2s", "3s", "avg"}, "l2_mean": {...}, "collision": {...}}

``miou_moving`` is the moving-class mIoU: the same per-class IoUs (same confusion matrices, same
``absent`` rule) averaged over the agent classes ``MOVING_CLASSES`` (bicycle, bus, car,
construction vehicle, motorcycle, pedestrian, trailer, truck), what a world model must move.

:func:`measure_speed` adds ``fps`` (the whole forecast at batch 1, ``model.forecast`` from the past
labels and poses, after warm-up), ``peak_memory_mb`` and ``params``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.utils.data import Dataset
from tqdm import tqdm

from t3fast.data.classes import MOVING_CLASSES
from t3fast.data.sample import NUM_FUTURE, PRESENT, DrivingBatch, collate_samples
from t3fast.evaluation.baselines import (
    constant_velocity,
    copy_paste,
    track_const_vel,
    track_gt_ego,
    warp_const_vel,
    warp_present,
)
from t3fast.evaluation.metrics import OccupancyMetrics
from t3fast.evaluation.planning import HORIZONS, PlanningMetrics
from t3fast.forecast.render import DecodeFrames
from t3fast.models.ego_motion import planar_poses
from t3fast.models.planner import constant_turn_rate
from t3fast.models.world_model import T3Former

OCC_KEYS = ("0s", "1s", "2s", "3s", "avg")
PLAN_KEYS = ("1s", "2s", "3s", "avg")


@dataclass
class MethodOutput:
    """What a method predicts for a batch of ``B`` windows (None: not predicted).

    Attributes:
        labels: uint8 ``[B, 6, X, Y, Z]`` future occupancy.
        actions: ``[B, 6, 2]`` planned displacements (present frame).
        reconstruction: uint8 ``[B, X, Y, Z]`` the present frame through the latent.
    """

    labels: Tensor | None = None
    actions: Tensor | None = None
    reconstruction: Tensor | None = None


Method = Callable[[DrivingBatch], MethodOutput]


class SharedRollout:
    """One forecasting pass per batch, shared by the rows of one model (``t3former``,
    ``_gt_ego``, ``_decoded``): the forecaster does not read the ego's motion, so those rows
    differ only in the poses their frames are rendered from and in keeping the observed
    world. Holds the last batch's stages' results (rows are scored batch by batch, see
    :func:`evaluate_many`). A planner that reads the route command gets the batch's unless
    ``command`` is False (the rows without it)."""

    def __init__(self, model: T3Former, command: bool = True):
        self.model = model
        self.command = command and model.reads_command
        self._batch: DrivingBatch | None = None
        self._out: dict = {}

    def __call__(self, batch: DrivingBatch) -> dict:
        """``{"past", "scene", "moves", "plan", "reconstruction"}`` of ``batch``: the stages of
        the model's forecast (:mod:`t3fast.forecast`) up to the render, and the present frame
        through the latent."""
        if batch is not self._batch:
            pipeline = self.model.pipeline
            past = pipeline.encode(batch.past_occ, batch.ego_poses[:, : PRESENT + 1])
            agents = pipeline.agents(past)
            scene = pipeline.scene(past, agents, NUM_FUTURE)
            moves = pipeline.motion(past, agents, scene) if pipeline.motion is not None else None
            plan = pipeline.plan(past, scene, batch.command if self.command else None)
            self._out = dict(past=past, scene=scene, moves=moves, plan=plan,
                             reconstruction=self.model.decoder.predict(past.present_planes))
            self._batch = batch
        return self._out


def t3former_method(
    model: T3Former, gt_ego: bool = False, keep_static: bool = True, shared: SharedRollout | None = None
) -> Method:
    """The world model: encode the 5 past frames (moved into the present frame with the past
    poses when the model is ego-aligned), forecast 6 steps, plan. ``gt_ego``: the steered
    forecast along the TRUE future poses (uses ground-truth ego motion). ``keep_static=False``:
    decoded frames only, without the observed static world (``observed_static``). ``shared``:
    a :class:`SharedRollout` of ``model`` the method reads its forecast from."""
    shared = SharedRollout(model) if shared is None else shared
    render = model.pipeline.render if keep_static else DecodeFrames(model.decoder, model.ego_aligned)

    def run(batch: DrivingBatch) -> MethodOutput:
        out = shared(batch)
        poses = planar_poses(batch.ego_poses, PRESENT)[:, PRESENT + 1 :] if gt_ego else out["plan"].poses
        labels = render(out["past"], out["scene"], out["moves"], poses)
        return MethodOutput(labels, None if gt_ego else out["plan"].actions, out["reconstruction"])

    return run


def copy_paste_method(batch: DrivingBatch) -> MethodOutput:
    """Copy&Paste: the present frame repeated; no plan."""
    return MethodOutput(labels=copy_paste(batch.past_occ, NUM_FUTURE))


def constant_velocity_method(batch: DrivingBatch) -> MethodOutput:
    """Constant-velocity ego motion; no occupancy."""
    return MethodOutput(actions=constant_velocity(batch.past_actions, NUM_FUTURE))


def constant_turn_rate_method(batch: DrivingBatch) -> MethodOutput:
    """Constant speed and turn rate (the untrained planner's plan); no occupancy."""
    return MethodOutput(actions=constant_turn_rate(batch.past_actions, NUM_FUTURE))


def warp_const_vel_method(batch: DrivingBatch) -> MethodOutput:
    """The present frame moved into each future ego frame, poses extrapolated at constant
    velocity and yaw rate from the past poses; no plan."""
    return MethodOutput(labels=warp_const_vel(batch.past_occ, batch.ego_poses, NUM_FUTURE))


def warp_gt_ego_method(batch: DrivingBatch) -> MethodOutput:
    """The present frame moved into each future ego frame with the TRUE future poses (uses
    ground-truth ego motion: a reference for what geometry alone gives, not a forecaster)."""
    future = planar_poses(batch.ego_poses, PRESENT)[:, PRESENT + 1 :]
    return MethodOutput(labels=warp_present(batch.past_occ, future))


def track_const_vel_method(batch: DrivingBatch) -> MethodOutput:
    """Classical tracker: each agent's BEV component moved along its velocity between the last
    two past frames (after ego compensation), then the scene moved into each future ego frame
    with poses extrapolated at constant velocity and yaw rate (past information only); no plan."""
    return MethodOutput(labels=track_const_vel(batch.past_occ, batch.ego_poses, NUM_FUTURE))


def track_gt_ego_method(batch: DrivingBatch) -> MethodOutput:
    """The tracker of :func:`track_const_vel_method` moved into the TRUE future ego frames (uses
    ground-truth ego motion); no plan."""
    return MethodOutput(labels=track_gt_ego(batch.past_occ, batch.ego_poses, NUM_FUTURE))


def _summaries(
    occ: dict[str, OccupancyMetrics] | None, plan: PlanningMetrics | None, absent: str = "one"
) -> dict:
    record: dict = {}
    for key in ("miou", "miou_moving", "iou"):
        if occ is None:
            record[key] = dict.fromkeys(OCC_KEYS)
            continue
        if key == "miou":
            values = {h: (None if m is None else 100 * m.miou(absent)) for h, m in occ.items()}
        elif key == "miou_moving":
            values = {h: (None if m is None else 100 * m.miou(absent, MOVING_CLASSES)) for h, m in occ.items()}
        else:
            values = {h: (None if m is None else m.summary()[key]) for h, m in occ.items()}
        values["avg"] = sum(values[h] for h in HORIZONS) / len(HORIZONS)
        record[key] = {k: values[k] for k in OCC_KEYS}
    planning = plan.summary() if plan is not None else {}
    for key in ("l2_at", "l2_mean", "collision"):
        record[key] = planning.get(key, dict.fromkeys(PLAN_KEYS))
    return record


@torch.no_grad()
def evaluate_many(
    methods: Mapping[str, Method],
    dataset: Dataset,
    indices: list[int] | None = None,
    batch_size: int = 1,
    device: torch.device | str = "cpu",
    use_mask: bool = False,
    progress: bool = True,
    desc: str = "evaluate",
    absent: str = "one",
) -> dict[str, dict]:
    """Score every method of ``methods`` on the windows ``indices`` of ``dataset``
    (``DrivingSample`` items) in one pass over them: each window is loaded once and every
    method sees the same batch object (so rows of one model can share its forecast,
    :class:`SharedRollout`). Returns ``{name: record}``.

    Occupancy: one confusion matrix per horizon (1 s, 2 s, 3 s = future frames 2, 4, 6) over
    the whole set, "0 s" from the method's reconstruction of the present frame, "avg" the
    mean of 1-3 s. ``use_mask`` scores only voxels in Occ3D's ``mask_camera``. ``absent``: how
    a class without ground truth counts in mIoU ("one": OccWorld's protocol; "skip": left out,
    for small validation sets where "one" inflates the score).
    """
    indices = list(range(len(dataset))) if indices is None else indices
    occ: dict[str, dict[str, OccupancyMetrics | None] | None] = dict.fromkeys(methods)
    plan: dict[str, PlanningMetrics | None] = dict.fromkeys(methods)
    batches = [indices[i : i + batch_size] for i in range(0, len(indices), batch_size)]
    for chunk in tqdm(batches, desc=desc, unit="batch", disable=not progress, leave=False):
        batch = collate_samples([dataset[i] for i in chunk]).to(device)
        mask = batch.mask_camera if use_mask else None
        for name, method in methods.items():
            out = method(batch)
            if out.labels is not None:
                if occ[name] is None:
                    occ[name] = {"0s": None, **{h: OccupancyMetrics(device=device) for h in HORIZONS}}
                scores = occ[name]
                for h, step in HORIZONS.items():
                    frame = PRESENT + step
                    scores[h].update(out.labels[:, step - 1], batch.occ[:, frame],
                                     None if mask is None else mask[:, frame])
                if out.reconstruction is not None:
                    scores["0s"] = scores["0s"] or OccupancyMetrics(device=device)
                    scores["0s"].update(out.reconstruction, batch.occ[:, PRESENT],
                                        None if mask is None else mask[:, PRESENT])
            if out.actions is not None:
                plan[name] = plan[name] or PlanningMetrics()
                future = slice(PRESENT + 1, None)
                plan[name].update(out.actions.cumsum(1), batch.future_actions.cumsum(1), batch.boxes[:, future],
                                  batch.box_valid[:, future], batch.box_labels)
    return {name: _summaries(occ[name], plan[name], absent) for name in methods}


def evaluate_forecasts(method: Method, dataset: Dataset, indices: list[int] | None = None, **options) -> dict:
    """:func:`evaluate_many` of one method; its record."""
    return evaluate_many({"method": method}, dataset, indices, **options)["method"]


def _peak_rss_mb() -> float | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _reset_peak_rss() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


@torch.no_grad()
def measure_speed(model: T3Former, sample_batch: DrivingBatch, warmup: int = 1, iters: int = 3) -> dict:
    """``{"fps", "peak_memory_mb", "params"}`` of the whole forecast at batch 1.

    The timed call is ``model.forecast(past_occupancy, past_motion)`` on the first window's past
    labels and poses, what a user calls: encoding the past frames into the present frame, the
    agents' velocities and fitted boxes, the forecaster, the planner (without a route command)
    and the 6 future frames rendered to labels; the mean of ``iters`` calls after ``warmup``.
    Peak memory: on CUDA the allocator's peak during the calls (tensors only, weights
    included); on CPU the peak resident set of the whole process during them (Linux; weights,
    libraries and interpreter included), else None.
    """
    model.eval()
    device = next(model.parameters()).device
    batch = sample_batch.to(device)
    past_occupancy, past_poses = batch.past_occ[:1], batch.ego_poses[:1, : PRESENT + 1]

    def step() -> None:
        model.forecast(past_occupancy, past_poses)
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    for _ in range(warmup):
        step()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    resettable = device.type == "cpu" and _reset_peak_rss()
    start = time.perf_counter()
    for _ in range(iters):
        step()
    elapsed = (time.perf_counter() - start) / iters
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2**20
    else:
        peak = _peak_rss_mb() if resettable else None
    return {"fps": 1.0 / elapsed, "peak_memory_mb": peak, "params": sum(p.numel() for p in model.parameters())}
