"""The stage-1 :class:`~t3fast.training.task.Task`: trains the triplane autoencoder on single
frames and scores its reconstruction."""

from __future__ import annotations

import copy
import dataclasses

import torch
from torch import Tensor, nn
from torch.utils.data import Dataset

from t3fast.data.classes import NUM_CLASSES
from t3fast.evaluation.reconstruction import evaluate_reconstruction
from t3fast.io.checkpoint import load_checkpoint
from t3fast.io.config import config_to_dict
from t3fast.models.autoencoder import TriplaneAutoencoder
from t3fast.training.autoencoder.frames import frames_dataset
from t3fast.training.configs import Stage1Config
from t3fast.training.losses import class_frequency_weights, occupancy_loss
from t3fast.training.sampling import sample_query_points


class AutoencoderTask:
    """Trains :class:`TriplaneAutoencoder` on single frames; scores reconstruction mIoU."""

    def __init__(self, cfg: Stage1Config):
        self.cfg = copy.deepcopy(cfg)
        self._val = None
        self._class_weights: Tensor | None = None

    def build_model(self) -> nn.Module:
        model = TriplaneAutoencoder(self.cfg.model, decoder_backend=self.cfg.decoder_backend)
        if self.cfg.init_from:
            weights = load_checkpoint(self.cfg.init_from)["model"]
            parts = {k: v.float() for k, v in weights.items() if k.split(".", 1)[0] in ("encoder", "decoder")}
            try:
                model.load_state_dict(parts)
            except RuntimeError as exc:
                raise ValueError(f"init_from={self.cfg.init_from!r}: its encoder/decoder do not fit this "
                                 f"model's config ({str(exc).splitlines()[0]})") from exc
        return model

    def train_dataset(self) -> Dataset:
        return frames_dataset(self.cfg.data, "train")

    def collate(self, batch_list: list[Tensor]) -> Tensor:
        return torch.stack(batch_list)

    def samples_in(self, batch: Tensor) -> int:
        return batch.shape[0]

    def training_step(self, model: nn.Module, labels: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        loss_cfg = self.cfg.loss
        if loss_cfg.full_grid:
            logits, targets = model(labels), labels.long()
        else:
            points, targets = sample_query_points(
                labels, loss_cfg.num_occupied, loss_cfg.num_near_free, loss_cfg.num_far_free
            )
            logits = model(labels, points)
        weights = self._weights(labels.device) if loss_cfg.class_weights else None
        loss, parts = occupancy_loss(logits, targets, class_weights=weights, lovasz_weight=loss_cfg.lovasz_weight)
        return loss, {k: v.detach() for k, v in parts.items()}

    def _weights(self, device: torch.device) -> Tensor:
        """Class-frequency weights from the first training frames (computed once; no flips,
        so the random streams of training are untouched)."""
        if self._class_weights is None:
            frames = frames_dataset(dataclasses.replace(self.cfg.data, flip=False), "train")
            n = min(len(frames), self.cfg.loss.class_weight_frames)
            counts = sum(torch.bincount(frames[i].long().flatten(), minlength=256)[:NUM_CLASSES] for i in range(n))
            self._class_weights = class_frequency_weights(counts)
        return self._class_weights.to(device)

    def evaluate(self, model: nn.Module) -> dict[str, float]:
        if self._val is None:
            self._val = frames_dataset(self.cfg.data, "val")
        indices = list(range(0, len(self._val), self.cfg.data.val_stride))
        device = next(model.parameters()).device
        metrics = evaluate_reconstruction(model, self._val, indices, device=device, progress=False)
        metrics.all_reduce()
        summary = metrics.summary()
        return {"score": summary["miou"], "miou": summary["miou"], "iou": summary["iou"]}

    def config_dict(self) -> dict:
        return config_to_dict(self.cfg)
