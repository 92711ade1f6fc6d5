"""The triplane autoencoder of stage 1: encoder + decoder."""

from __future__ import annotations

from torch import Tensor, nn

from t3fast.models.config import AutoencoderConfig
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.encoder import TriplaneEncoder
from t3fast.models.triplane import Triplane


class TriplaneAutoencoder(nn.Module):
    """``labels [B, X, Y, Z]`` -> :class:`Triplane` -> logits, for pretraining the latent."""

    def __init__(self, config: AutoencoderConfig, decoder_backend: str = "fused"):
        super().__init__()
        self.config = config
        self.encoder = TriplaneEncoder(config)
        self.decoder = TriplaneDecoder.from_config(config, backend=decoder_backend)

    def encode(self, labels: Tensor) -> Triplane:
        return self.encoder(labels)

    def forward(self, labels: Tensor, points: Tensor | None = None) -> Tensor:
        """Logits ``[B, N, K]`` at ``points`` ``[B, N, 3]``, or of the full grid."""
        return self.decoder(self.encoder(labels), points)

    def reconstruct(self, labels: Tensor) -> Tensor:
        """uint8 labels of the reconstructed grid."""
        return self.decoder.predict(self.encoder(labels))
