"""Reconstruction quality of a triplane autoencoder (the papers' "0 s" column)."""

from __future__ import annotations

import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from t3fast.evaluation.metrics import OccupancyMetrics
from t3fast.models.autoencoder import TriplaneAutoencoder


@torch.no_grad()
def evaluate_reconstruction(
    model: TriplaneAutoencoder,
    frames: Dataset,
    indices: list[int] | None = None,
    batch_size: int = 2,
    device: torch.device | str = "cpu",
    progress: bool = True,
) -> OccupancyMetrics:
    """Encodes and decodes every frame (``uint8 [X, Y, Z]`` items of ``frames``) through the
    argmax mode and accumulates the confusion matrix against the input labels."""
    model.eval()
    indices = list(range(len(frames))) if indices is None else indices
    metrics = OccupancyMetrics(device=device)
    batches = [indices[i : i + batch_size] for i in range(0, len(indices), batch_size)]
    for batch in tqdm(batches, desc="reconstruct", unit="batch", disable=not progress):
        labels = torch.stack([frames[i] for i in batch]).to(device)
        metrics.update(model.reconstruct(labels), labels)
    return metrics
