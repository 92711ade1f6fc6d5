"""TriplaneEncoder: occupancy labels -> triplane."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from t3fast.data.classes import FREE, IGNORE
from t3fast.host_syncs import reads_host
from t3fast.models.blocks import ResBlock3d, group_norm, norm_silu
from t3fast.models.config import AutoencoderConfig
from t3fast.models.triplane import Triplane
from t3fast.ops import axis_pool, label_conv3d


def check_labels(labels: Tensor, grid: tuple[int, int, int], num_classes: int) -> None:
    """Raises ValueError unless ``labels`` is an integer ``[B, *grid]`` tensor of class ids
    in ``0 .. num_classes - 1`` or the ignore id 255. The ids are read where the host is read
    (:func:`~t3fast.host_syncs.reads_host`: the CPU); on a GPU that read would stall every
    encoding, and the callers check them once (the forecast its inputs, the data its files)."""
    if labels.dim() != 4 or tuple(labels.shape[1:]) != tuple(grid):
        raise ValueError(f"labels must have shape [B, {', '.join(map(str, grid))}], got {list(labels.shape)}")
    if labels.is_floating_point() or labels.is_complex() or labels.dtype == torch.bool:
        raise ValueError(f"labels must be an integer tensor of class ids, got {labels.dtype}")
    if not reads_host(labels.device):
        return
    bad = ((labels < 0) | (labels >= num_classes)) & (labels != IGNORE)
    if bool(bad.any()):
        raise ValueError(
            f"labels must be class ids in 0..{num_classes - 1} or {IGNORE} (ignore), "
            f"got {labels[bad].unique()[:8].tolist()}"
        )


class TriplaneEncoder(nn.Module):
    """Encodes occupancy labels into a bounded triplane.

    Class embedding -> stem conv and residual 3D blocks at full resolution -> a (2, 2, 1)
    strided downsample (200 x 200 x 16 -> 100 x 100 x 16) -> residual 3D blocks ->
    projection to C channels -> ``axis_pool`` (one read of the volume) -> per-plane
    GroupNorm + tanh, which keeps every latent value in (-1, 1) for the forecaster.
    With ``config.latent == "bev"`` only the xy plane is produced (``xz``/``yz`` are None).

    The embedding and the stem convolution run as one :func:`~t3fast.ops.label_conv3d` (27
    table lookups per voxel), and each GroupNorm with the activation after it (and a residual
    block's sum) as one :func:`~t3fast.ops.group_norm_silu`, with ``backend="fused"``;
    ``"reference"`` runs them as the ``nn.Embedding``, ``nn.Conv3d``, ``nn.GroupNorm`` and
    ``nn.SiLU`` they are (same weights, same results to rounding).

    Args:
        config: sizes; the default is the papers' (``AutoencoderConfig()``).
        backend: ``"fused"`` or ``"reference"``.

    Input ``labels [B, X, Y, Z]`` (integer class ids, 255 = ignore, treated as free);
    output a :class:`Triplane` ``xy [B, C, X', Y']``, ``xz [B, C, X', Z']``, ``yz [B, C, Y', Z']``.
    """

    def __init__(self, config: AutoencoderConfig | None = None, backend: str = "fused"):
        super().__init__()
        if backend not in ("fused", "reference"):
            raise ValueError(f"backend must be 'fused' or 'reference', got {backend!r}")
        cfg = config or AutoencoderConfig()
        self.config = cfg
        self.backend = backend
        full, half = cfg.full_res_channels, cfg.half_res_channels
        self.embed = nn.Embedding(cfg.num_classes, cfg.embed_dim)
        self.stem = nn.Sequential(
            nn.Conv3d(cfg.embed_dim, full, 3, padding=1, bias=False), group_norm(full), nn.SiLU(inplace=True)
        )
        self.full_res = nn.Sequential(*[ResBlock3d(full) for _ in range(cfg.full_res_blocks)])
        self.down = nn.Sequential(
            nn.Conv3d(full, half, kernel_size=(2, 2, 1), stride=(2, 2, 1), bias=False), group_norm(half),
            nn.SiLU(inplace=True),
        )
        self.half_res = nn.Sequential(*[ResBlock3d(half) for _ in range(cfg.half_res_blocks)])
        self.proj = nn.Conv3d(half, cfg.channels, 1)
        planes = 1 if cfg.latent == "bev" else 3
        self.plane_norms = nn.ModuleList(nn.GroupNorm(1, cfg.channels) for _ in range(planes))

    def volume(self, labels: Tensor) -> Tensor:
        """The encoded volume ``[B, C, X', Y', Z']`` before pooling."""
        check_labels(labels, self.config.grid, self.config.num_classes)
        ids = labels.masked_fill(labels == IGNORE, FREE)
        fused = self.backend == "fused"
        x = norm_silu(self.stem[1], self.stem[2], self.stem_conv(ids), fused=fused)
        for block in self.full_res:
            x = block(x, fused)
        x = norm_silu(self.down[1], self.down[2], self.down[0](x), fused=fused)
        for block in self.half_res:
            x = block(x, fused)
        return self.proj(x)

    def stem_conv(self, ids: Tensor) -> Tensor:
        """The stem convolution of the embedded class ids ``[B, X, Y, Z]`` -> ``[B, F, X, Y, Z]``
        (contiguous: the CPU GroupNorm that follows loses precision on a channels-last input)."""
        conv = self.stem[0]
        if self.backend == "reference":
            return conv(self.embed(ids.long()).permute(0, 4, 1, 2, 3).contiguous())
        table = torch.einsum("ceijk,qe->ijkqc", conv.weight, self.embed.weight)
        if ids.dtype not in (torch.uint8, torch.int32, torch.int64):
            ids = ids.long()
        return label_conv3d(ids, table.reshape(27, *table.shape[3:]))

    def forward(self, labels: Tensor) -> Triplane:
        volume = self.volume(labels)
        if self.config.latent == "bev":
            return Triplane(torch.tanh(self.plane_norms[0](volume.mean(dim=4))), None, None)
        planes = axis_pool(volume)
        return Triplane(*(torch.tanh(norm(p)) for norm, p in zip(self.plane_norms, planes)))
