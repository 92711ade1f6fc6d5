"""Semantic occupancy metrics: per-class IoU, mIoU and binary occupied/free IoU.

The protocol follows what OccWorld's published evaluation code computes
(``utils/metric_util.py`` and ``eval_metric_stp3.py`` of wzzheng/OccWorld):

* per-class IoU over the 17 semantic classes 0..16 (``free`` excluded), accumulated
  over the whole evaluation set (not averaged per frame);
* mIoU = mean of those 17 IoUs, where a class with **no ground-truth voxel** in the
  accumulated set counts as IoU 1 (OccWorld appends ``1`` when ``total_seen == 0``,
  whatever was predicted). Over a full validation split every class is present and
  this never triggers; on small sets it inflates mIoU, so :meth:`OccupancyMetrics.miou`
  also offers ``absent="skip"`` and :meth:`OccupancyMetrics.summary` lists the classes
  it concerned;
* IoU = IoU of the binary class "occupied" (label != free) against free.

Differences from OccWorld, all deliberate: voxels whose target is ``ignore_index``
(255) are never scored, also in the binary IoU (OccWorld maps every label != 17 to
"occupied" before its ignore check); an optional boolean mask (Occ3D ``mask_camera``)
restricts scoring; the statistics are one int64 confusion matrix, so counts stay exact
beyond 2^24 voxels (OccWorld accumulates float32 counts).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import torch
import torch.distributed as dist

from t3fast.data.classes import CLASS_NAMES, FREE, IGNORE, NUM_CLASSES

__all__ = ["OccupancyMetrics"]


class OccupancyMetrics:
    """Confusion-matrix accumulator for semantic occupancy.

    ``confusion[t, p]`` counts scored voxels with target class ``t`` and predicted
    class ``p`` (int64 ``[num_classes, num_classes]``). Every class except
    ``free_class`` is a semantic class for mIoU and "occupied" for the binary IoU.

    Args:
        num_classes: number of label values, free included (18 for Occ3D).
        free_class: the label of empty space (17).
        ignore_index: target value that is never scored (255).
        device: where the matrix lives (the CPU by default). Updates may come from any device.
        class_names: one name per class, used by :meth:`summary` and :meth:`table`.
    """

    def __init__(
        self,
        num_classes: int = NUM_CLASSES,
        free_class: int = FREE,
        ignore_index: int = IGNORE,
        device: torch.device | str = "cpu",
        class_names: tuple[str, ...] | None = None,
    ) -> None:
        if not 0 <= free_class < num_classes:
            raise ValueError(f"free_class {free_class} is outside [0, {num_classes})")
        if 0 <= ignore_index < num_classes:
            raise ValueError(f"ignore_index {ignore_index} collides with a class id in [0, {num_classes})")
        names = class_names if class_names is not None else CLASS_NAMES
        if len(names) != num_classes:
            raise ValueError(f"class_names has {len(names)} names, expected num_classes = {num_classes}")
        self.num_classes = num_classes
        self.free_class = free_class
        self.ignore_index = ignore_index
        self.class_names = tuple(names)
        self.confusion = torch.zeros(num_classes, num_classes, dtype=torch.int64, device=device)
        semantic = [c for c in range(num_classes) if c != free_class]
        self._semantic = torch.tensor(semantic, dtype=torch.long, device="cpu")

    # accumulation

    def update(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Add one batch.

        Args:
            pred: predicted labels, any integer dtype (uint8 included), any shape, e.g. ``[B, X, Y, Z]``.
            target: ground-truth labels, same shape; ``ignore_index`` marks unscored voxels.
            mask: optional bool (or 0/1 integer) tensor of the same shape; only true voxels are scored.

        Raises:
            ValueError: on a shape mismatch, a non-integer dtype or a label out of range.
        """
        self._check(pred, target, mask)
        pred = pred.reshape(-1).long()
        target = target.reshape(-1).long()
        keep = target != self.ignore_index
        if mask is not None:
            keep &= mask.reshape(-1).to(device=keep.device, dtype=torch.bool)
        # one bincount over the flat (target, pred) pair index builds the whole matrix
        pairs = target[keep] * self.num_classes + pred.to(target.device)[keep]
        counts = torch.bincount(pairs, minlength=self.num_classes**2)
        self.confusion += counts.view(self.num_classes, self.num_classes).to(self.confusion.device)

    def _check(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None) -> None:
        for name, t in (("pred", pred), ("target", target)):
            if t.dtype.is_floating_point or t.dtype.is_complex or t.dtype == torch.bool:
                raise ValueError(f"OccupancyMetrics.update: {name} must have an integer dtype, got {t.dtype}")
        if pred.shape != target.shape:
            raise ValueError(
                f"OccupancyMetrics.update: pred shape {tuple(pred.shape)} != target shape {tuple(target.shape)}"
            )
        if mask is not None and mask.shape != target.shape:
            raise ValueError(
                f"OccupancyMetrics.update: mask shape {tuple(mask.shape)} != target shape {tuple(target.shape)}"
            )
        if pred.numel() == 0:
            return
        lo, hi = int(pred.min()), int(pred.max())
        if lo < 0 or hi >= self.num_classes:
            raise ValueError(
                f"OccupancyMetrics.update: pred labels must lie in [0, {self.num_classes}), got [{lo}, {hi}]"
            )
        bad = (target < 0) | ((target >= self.num_classes) & (target != self.ignore_index))
        if bool(bad.any()):
            value = int(target[bad][0])
            raise ValueError(
                f"OccupancyMetrics.update: target label {value} is neither in [0, {self.num_classes}) "
                f"nor ignore_index {self.ignore_index}"
            )

    def merge(self, other: OccupancyMetrics) -> OccupancyMetrics:
        """Add the counts of ``other`` (same class layout) into this accumulator; returns ``self``."""
        if other.confusion.shape != self.confusion.shape or other.free_class != self.free_class:
            raise ValueError(
                f"OccupancyMetrics.merge: incompatible accumulators ({other.num_classes} classes, free "
                f"{other.free_class}) vs ({self.num_classes} classes, free {self.free_class})"
            )
        self.confusion += other.confusion.to(self.confusion.device)
        return self

    def all_reduce(self) -> OccupancyMetrics:
        """Sum the matrix over all processes when ``torch.distributed`` is initialised; returns ``self``."""
        if dist.is_available() and dist.is_initialized():
            # NCCL only reduces CUDA tensors; gloo takes CPU ones
            device = torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else "cpu"
            buffer = self.confusion.to(device)
            dist.all_reduce(buffer, op=dist.ReduceOp.SUM)
            self.confusion.copy_(buffer)
        return self

    def reset(self) -> None:
        """Zero the counts."""
        self.confusion.zero_()

    # results

    def per_class_iou(self) -> torch.Tensor:
        """IoU of each semantic class, float64 ``[num_classes - 1]`` (free left out).

        ``TP / (TP + FP + FN)``; NaN for a class that appears in neither prediction nor target.
        """
        conf = self.confusion.double()
        tp = conf.diagonal()
        union = conf.sum(0) + conf.sum(1) - tp
        iou = torch.where(union > 0, tp / union.clamp(min=1), torch.full_like(tp, math.nan))
        return iou[self._semantic.to(iou.device)].cpu()

    def _has_target(self) -> torch.Tensor:
        """bool ``[num_classes - 1]``: whether each semantic class has a scored ground-truth voxel."""
        return self.confusion.sum(1).cpu()[self._semantic] > 0

    def absent_classes(self) -> list[int]:
        """Semantic class ids that have no scored ground-truth voxel."""
        return self._semantic[~self._has_target()].tolist()

    def miou(self, absent: Literal["one", "skip"] = "one", classes: Sequence[int] | None = None) -> float:
        """Mean IoU over the semantic classes, as a fraction.

        Args:
            absent: how a class with no ground-truth voxel counts. ``"one"`` (default) is
                OccWorld's convention: IoU 1, even if it was predicted. ``"skip"`` leaves it out
                of the mean (NaN when no class has ground truth).
            classes: average over these semantic class ids only (e.g. ``MOVING_CLASSES`` for
                the moving-class mIoU); the IoUs and the ``absent`` rule are the same.
        """
        iou = self.per_class_iou()
        present = self._has_target()
        if classes is not None:
            semantic = self._semantic.tolist()
            if not classes or any(c not in semantic for c in classes):
                raise ValueError(f"classes must be a non-empty subset of the semantic classes {semantic}, "
                                 f"got {list(classes)}")
            pick = torch.tensor([semantic.index(c) for c in classes], dtype=torch.long, device="cpu")
            iou, present = iou[pick], present[pick]
        if absent == "one":
            return float(torch.where(present, iou, torch.ones_like(iou)).mean())
        if absent == "skip":
            return float(iou[present].mean()) if bool(present.any()) else math.nan
        raise ValueError(f"absent must be 'one' or 'skip', got {absent!r}")

    def iou(self) -> float:
        """IoU of "occupied" (any class but free) against free, as a fraction; NaN with no occupied voxel."""
        conf = self.confusion
        sem = self._semantic.to(conf.device)
        tp = int(conf[sem][:, sem].sum())  # occupied predicted as any occupied class
        fn = int(conf[sem, self.free_class].sum())
        fp = int(conf[self.free_class, sem].sum())
        union = tp + fn + fp
        return tp / union if union > 0 else math.nan

    def summary(self) -> dict[str, object]:
        """Results in percent: ``{"miou", "iou", "per_class": {name: iou}, "absent": [names]}``.

        ``per_class`` holds the plain IoU (NaN where the class appears nowhere); ``absent``
        names the classes without ground truth, which ``miou`` counts as 100 (see module doc).
        """
        names = [self.class_names[c] for c in self._semantic.tolist()]
        return {
            "miou": 100.0 * self.miou(),
            "iou": 100.0 * self.iou(),
            "per_class": {n: 100.0 * float(v) for n, v in zip(names, self.per_class_iou())},
            "absent": [self.class_names[c] for c in self.absent_classes()],
        }

    def table(self) -> str:
        """Markdown table: one row per semantic class, then mIoU and IoU, in percent."""
        s = self.summary()
        absent = set(s["absent"])
        lines = ["| class | IoU (%) |", "|---|---:|"]
        for name, value in s["per_class"].items():
            note = " (no ground truth: 100 in mIoU)" if name in absent else ""
            lines.append(f"| {name} | {value:.2f}{note} |")
        lines.append(f"| **mIoU** | {s['miou']:.2f} |")
        lines.append(f"| **IoU** (occupied vs free) | {s['iou']:.2f} |")
        return "\n".join(lines)
