"""Occupancy losses: cross-entropy + Lovasz-softmax, and class-frequency weights."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from t3fast.data.classes import IGNORE

__all__ = ["class_frequency_weights", "lovasz_softmax", "occupancy_loss"]


def lovasz_softmax(
    probs: torch.Tensor,
    labels: torch.Tensor,
    ignore_index: int = IGNORE,
    classes: str | Sequence[int] = "present",
) -> torch.Tensor:
    """Lovasz-softmax loss (Berman, Rannen Triki, Blaschko, CVPR 2018), all classes at once.

    For each class ``c`` the per-point errors ``|1[label == c] - probs[:, c]|`` are sorted
    in decreasing order and dotted with the gradient of the Lovasz extension of the
    Jaccard loss; the result is averaged over the chosen classes. The classes are handled
    together: one ``torch.sort`` over the ``[K, P]`` error matrix.

    Args:
        probs: class probabilities ``[P, K]`` (softmax output), float.
        labels: targets ``[P]``, integer; ``ignore_index`` points are dropped.
        ignore_index: label value that is never a target.
        classes: ``"present"`` averages over classes that occur in ``labels``, ``"all"`` over all
            ``K``, or an explicit list of class ids.

    Returns:
        Scalar loss; 0 (still attached to ``probs``) when nothing is left to average.
    """
    if probs.dim() != 2 or labels.shape != probs.shape[:1]:
        raise ValueError(
            f"lovasz_softmax: expected probs [P, K] and labels [P], got {tuple(probs.shape)} and {tuple(labels.shape)}"
        )
    keep = labels != ignore_index
    # ignored points stay in place with no error and no class: after every point with an
    # error in the sorted order, they change no term (and nothing waits for the device)
    labels = torch.where(keep, labels.long(), 0)
    num_classes = probs.shape[1]
    fg = ((labels.unsqueeze(0) == torch.arange(num_classes, device=labels.device).unsqueeze(1)) & keep).to(probs.dtype)
    errors = (fg - probs.t()).abs() * keep  # [K, P]
    errors_sorted, order = torch.sort(errors, dim=1, descending=True)
    losses = (errors_sorted * _lovasz_grad(fg.gather(1, order))).sum(1)  # [K]
    chosen = _choose_classes(classes, fg, num_classes)
    return (losses * chosen).sum() / chosen.sum().clamp(min=1)  # 0, still attached, if none is chosen


def _lovasz_grad(fg_sorted: torch.Tensor) -> torch.Tensor:
    """Gradient of the Lovasz extension of the Jaccard loss, per row.

    Args:
        fg_sorted: ``[K, P]`` 0/1 ground truth in decreasing-error order.

    Returns:
        ``[K, P]`` weights ``J(i) - J(i - 1)`` with ``J(i)`` the Jaccard loss of the top ``i + 1`` errors.
    """
    gts = fg_sorted.sum(1, keepdim=True)
    intersection = gts - fg_sorted.cumsum(1)
    union = gts + (1.0 - fg_sorted).cumsum(1)  # >= 1 everywhere, no division by zero
    jaccard = 1.0 - intersection / union
    return torch.cat([jaccard[:, :1], jaccard[:, 1:] - jaccard[:, :-1]], dim=1)


def _choose_classes(classes: str | Sequence[int], fg: torch.Tensor, num_classes: int) -> torch.Tensor:
    """bool ``[K]`` of the classes to average over."""
    if classes == "present":
        return fg.sum(1) > 0
    if classes == "all":
        return torch.ones(num_classes, dtype=torch.bool, device=fg.device)
    if isinstance(classes, str):
        raise ValueError(f"lovasz_softmax: classes must be 'present', 'all' or a list of ids, got {classes!r}")
    chosen = torch.zeros(num_classes, dtype=torch.bool, device=fg.device)
    chosen[list(classes)] = True
    return chosen


def occupancy_loss(
    logits: torch.Tensor,
    labels: torch.Tensor,
    class_weights: torch.Tensor | None = None,
    lovasz_weight: float = 1.0,
    ignore_index: int = IGNORE,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Stage-1 occupancy loss: (weighted) cross-entropy + ``lovasz_weight`` * Lovasz-softmax.

    Args:
        logits: ``[..., K]`` class scores, e.g. ``[B, N, K]`` for sampled points or ``[B, X, Y, Z, K]``.
        labels: ``[...]`` integer targets (uint8 allowed); ``ignore_index`` is never a target.
        class_weights: optional ``[K]`` cross-entropy weights (see :func:`class_frequency_weights`).
        lovasz_weight: factor of the Lovasz term (``0`` skips it).
        ignore_index: label value that is never a target.

    Returns:
        ``(loss, {"ce": ..., "lovasz": ...})``, the parts detached. With no valid target the
        loss is 0 and still attached to ``logits``.
    """
    num_classes = logits.shape[-1]
    if logits.shape[:-1] != labels.shape:
        raise ValueError(f"occupancy_loss: logits {tuple(logits.shape)} do not match labels {tuple(labels.shape)}")
    flat_logits = logits.reshape(-1, num_classes).float()
    flat_labels = labels.reshape(-1).long()
    keep = flat_labels != ignore_index
    # the mean over the kept points, as cross_entropy's, without selecting them (no host read)
    target = torch.where(keep, flat_labels, 0)
    weight = class_weights.to(flat_logits) if class_weights is not None else None
    terms = F.cross_entropy(flat_logits, target, weight=weight, reduction="none") * keep
    kept = (weight[target] if weight is not None else torch.ones_like(terms)) * keep
    ce = terms.sum() / kept.sum().clamp(min=torch.finfo(terms.dtype).tiny)  # 0 with no target
    if lovasz_weight:
        lovasz = lovasz_softmax(flat_logits.softmax(-1), flat_labels, ignore_index=ignore_index)
    else:
        lovasz = flat_logits.new_zeros(())
    loss = ce + lovasz_weight * lovasz
    return loss, {"ce": ce.detach(), "lovasz": lovasz.detach()}


def class_frequency_weights(counts: torch.Tensor) -> torch.Tensor:
    """Inverse-log-frequency class weights, ``w_k = 1 / ln(n_k)``, float32 ``[K]``.

    This is the weighting of the BEVDet-occupancy / FlashOcc / SurroundOcc family
    (``1 / log(n_k + 0.001)`` on raw voxel counts): it tempers, rather than inverts, the
    imbalance (a class 10^4 times rarer gets about 2-3x the weight, not 10^4x). Counts
    are clamped to at least 2 so an unseen class gets a finite positive weight (the
    original turns negative below one voxel). With ``reduction="mean"`` cross-entropy
    only the ratios matter, so no normalisation is applied.

    Args:
        counts: ``[K]`` voxel count per class over the training set (any numeric dtype).
    """
    return 1.0 / torch.log(counts.double().clamp(min=2.0)).float()
