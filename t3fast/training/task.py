"""The contract between a training job and :class:`~t3fast.training.trainer.Trainer`."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch
from torch import nn
from torch.utils.data import Dataset


@runtime_checkable
class Task(Protocol):
    """What a training job supplies to :class:`Trainer`.

    Methods:
        build_model: the trainable module. The trainer moves it to the device and, when
            distributed, wraps it in DistributedDataParallel.
        train_dataset: a map-style dataset (with ``len``).
        collate: turns a list of dataset items into a batch. The trainer moves the batch's
            tensors (in dicts, lists, tuples, or objects with a ``.to(device)``) to the device.
        training_step: ``(model, batch) -> (loss, values)``: the scalar loss to back-propagate
            and the values to log (the same keys on every rank): floats, or 0-dim tensors,
            which the trainer reads after the backward, all at once (reading each in the step
            would make the host wait for the forward before it can launch the backward).
            ``model`` may be the DDP wrapper: compute the loss through ``model(...)`` so
            gradients are synchronised. Runs under autocast when AMP is on.
        evaluate: ``model -> metrics``; must contain ``"score"`` (higher is better; decides
            ``best.pt``). Called on every rank with the plain module in eval mode under
            ``torch.no_grad()``; the task may all-reduce. Logged by rank 0. Random numbers drawn
            here do not disturb the training streams.
        samples_in: number of samples in a batch, for throughput.

    Optional: ``config_dict() -> dict`` of plain values (numbers, strings, lists, dicts), stored in
    checkpoints under ``state["config"]["task"]``; ``lr_scales() -> {submodule name: factor}``,
    learning-rate multipliers of parts of the model (e.g. a decoder being fine-tuned);
    ``step_variant() -> hashable``, for ``train.cuda_graph``: draws the host-side choices of the
    next training step (e.g. where a rollout starts), which that step then uses, and returns
    them. Steps with the same variant and batch shapes must run the same kernels, read nothing
    back on the host and copy no host data to the device: the trainer replays one CUDA graph
    per variant (:mod:`t3fast.training.graphed_step`).
    """

    def build_model(self) -> nn.Module: ...

    def train_dataset(self) -> Dataset: ...

    def collate(self, batch_list: list[Any]) -> Any: ...

    def training_step(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, torch.Tensor | float]]: ...

    def evaluate(self, model: nn.Module) -> dict[str, float]: ...

    def samples_in(self, batch: Any) -> int: ...
