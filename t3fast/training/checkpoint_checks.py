"""What a training run checks before it goes on from a checkpoint or writes one: the file is a
readable training checkpoint of a model of this run's shape, and every number in it is finite.

Each problem is a one-line :class:`~t3fast.errors.CheckpointError` naming the file and what is
wrong, since a user resuming the wrong file (an exported model, a run of another size, a file
cut short) can fix it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from t3fast.errors import CheckpointError
from t3fast.io.checkpoint import first_nonfinite, load_readable_checkpoint

#: what the trainer writes into a checkpoint and needs back to go on from it
TRAINING_KEYS = ("model", "optimizer", "scheduler", "scaler", "step", "best_score", "rng")


def read_training_checkpoint(path: Path) -> dict[str, Any]:
    """The state saved by the trainer in ``path``, once it is known to be readable, complete and finite."""
    state = load_readable_checkpoint(path)
    _require_training_keys(state, path)
    _require_finite(state, path)
    return state


def load_weights(module: nn.Module, weights: Mapping[str, Any], path: Path) -> None:
    """``module.load_state_dict(weights)``; weights of another shape or name raise a
    :class:`~t3fast.errors.CheckpointError` naming the first wrong one instead of torch's list."""
    expected = {k: v.shape for k, v in module.state_dict().items()}
    try:
        module.load_state_dict(weights)
    except RuntimeError as exc:
        problems = weight_mismatches(expected, weights) or [(str(exc).strip().splitlines() or [""])[0]]
        more = len(problems) - 1
        count = f" (and {more} more wrong weight{'s' if more > 1 else ''})" if more else ""
        raise CheckpointError(f"{path}: {problems[0]}{count}: it was written by a run with other model "
                              "settings") from exc


def weight_mismatches(expected: Mapping[str, torch.Size], weights: Mapping[str, Any]) -> list[str]:
    """Each weight of ``weights`` that is missing, extra, not a tensor or of another shape than
    ``expected`` (this run's model), in the model's order, then the extra ones."""
    problems = []
    for key, shape in expected.items():
        got = weights.get(key)
        if got is None:
            problems.append(f"weight {key!r} is missing (this run's model has it with shape {list(shape)})")
        elif not isinstance(got, torch.Tensor):
            problems.append(f"weight {key!r} is a {type(got).__name__}, not a tensor")
        elif got.shape != shape:
            problems.append(f"weight {key!r} has shape {list(got.shape)} but this run's model has {list(shape)}")
    problems += [f"weight {key!r} is not part of this run's model" for key in weights if key not in expected]
    return problems


def _require_training_keys(state: Any, path: Path) -> None:
    missing = [k for k in TRAINING_KEYS if not (isinstance(state, dict) and k in state)]
    if not missing:
        if not isinstance(state["model"], dict):
            raise CheckpointError(f"{path}: its 'model' is a {type(state['model']).__name__}, not a dict of weights")
        return
    if isinstance(state, dict) and isinstance(state.get("model"), dict) and "optimizer" not in state:
        raise CheckpointError(f"{path}: an exported (inference) checkpoint, without the optimizer state training "
                              "needs to go on: resume from the run's last.pt")
    raise CheckpointError(f"{path}: not a training checkpoint (it has no {', '.join(map(repr, missing))}): "
                          "resume from a run's last.pt")


def _require_finite(state: dict[str, Any], path: Path) -> None:
    """Going on from NaN or infinite weights (or Adam moments) only trains NaNs."""
    advice = "a run cannot be resumed from it (resume from an earlier checkpoint or start a new run)"
    bad = first_nonfinite(state["model"])
    if bad is not None:
        raise CheckpointError(f"{path}: weight {bad!r} is not finite; {advice}")
    optimizer = state["optimizer"]
    per_param = optimizer.get("state", {}) if isinstance(optimizer, dict) else {}
    moments = {f"state.{i}.{k}": v for i, s in per_param.items() if isinstance(s, dict) for k, v in s.items()}
    bad = first_nonfinite(moments)
    if bad is not None:
        raise CheckpointError(f"{path}: optimizer state {bad!r} is not finite; {advice}")
