"""The box motion network's loss and error: how far each agent's box lands from its true place."""

from __future__ import annotations

import torch
from torch import Tensor

from t3fast.agents.box_kinematics import BOX_CLASSES
from t3fast.models.ego_motion import wrap_angle

CLASS_SLICE = slice(-2 - len(BOX_CLASSES), -2)  # the class one-hot in the kinematics


def landing_errors(displacement: Tensor, turn: Tensor, fields: dict[str, Tensor]) -> Tensor:
    """Per agent and future step, metres between the predicted and the true box: the centre's
    miss plus the yaw's miss at half the box length (where a wrong heading shows). Predictions:
    ``displacement`` ``[n, S, 2]`` (present frame) and ``turn`` ``[n, S]``; ``fields`` holds the
    truth (see :class:`~t3fast.training.box_motion.box_cache.BoxMotionSamples`). ``[n, S]``."""
    centre = (displacement - fields["displacement"]).norm(dim=-1)
    half_length = fields["features"][:, -2:-1] / 2
    return centre + wrap_angle(turn - fields["turn"]).abs() * half_length


def class_balanced_mean(errors: Tensor, fields: dict[str, Tensor]) -> Tensor:
    """Mean of ``errors`` ``[n, S]`` over the valid steps of each class, averaged over the classes
    present: every class counts alike, as in the moving-class mIoU (pedestrians outnumber the
    other classes several times)."""
    classes = fields["features"][:, CLASS_SLICE]  # [n, K]
    valid = fields["valid"].to(errors.dtype)
    per_class_sum = classes.T @ (errors * valid).sum(1)
    per_class_count = classes.T @ valid.sum(1)
    present = per_class_count > 0
    means = per_class_sum / per_class_count.clamp(min=1) * present  # 0 for a class absent here
    classes_present = present.sum()
    # no class present: 0, still a function of the errors (a batch without agents trains nothing);
    # no mask or branch on the values, so the step never waits on the device
    return torch.where(classes_present > 0, means.sum() / classes_present.clamp(min=1), errors.sum() * 0)
