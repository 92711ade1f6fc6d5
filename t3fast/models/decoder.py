"""TriplaneDecoder: triplane -> occupancy logits or labels, through the fused decode op."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

import t3fast.ops as fused_ops
from t3fast.data.classes import GRID_SHAPE, NUM_CLASSES
from t3fast.models.blocks import PlaneRefiner
from t3fast.models.config import MAX_PE_FREQS, AutoencoderConfig
from t3fast.models.triplane import Triplane
from t3fast.ops import reference as reference_ops


class TriplaneDecoder(nn.Module):
    """Decodes a triplane into semantic occupancy.

    Each plane is optionally refined by its own 2D conv block (``in_channels`` ->
    ``feature_channels``); then, for every query point, the three planes are looked up
    bilinearly, summed, concatenated with a sin/cos encoding of the point, and an MLP gives
    class logits: all of it one fused op (:func:`t3fast.ops.triplane_decode`).

    Args:
        in_channels: channels C of the input planes.
        feature_channels: channels C_f after refinement (must equal ``in_channels`` when
            ``refine`` is False).
        hidden: widths of the MLP's hidden layers (ReLU between layers).
        num_classes: output classes (18 for Occ3D).
        pe_freqs: encoding frequencies F (6 F encoding values per point).
        grid: ``(X, Y, Z)`` decoded by ``forward`` without points and by ``predict``.
        refine: use the per-plane conv refinement.
        bev: decode a BEV-only latent (the xy plane alone; ``xz``/``yz`` are None).
        backend: ``"fused"`` (the compiled kernels) or ``"reference"`` (pure PyTorch, same
            results, much more memory).

    The defaults are the papers' decoder for Occ3D-nuScenes (C = 8, C_f = 64, hidden
    256 x 4). The state_dict is plain: ``refiners.{0,1,2}.*`` and ``mlp.{i}.weight/bias``.

    Example::

        decoder = TriplaneDecoder()
        logits = decoder(triplane)                   # [B, 200, 200, 16, 18]
        logits = decoder(triplane, points=points)    # points [B, N, 3] in [-1, 1] -> [B, N, 18]
        labels = decoder.predict(triplane)           # uint8 [B, 200, 200, 16]
    """

    def __init__(
        self,
        in_channels: int = 8,
        feature_channels: int = 64,
        hidden: Sequence[int] = (256, 256, 256, 256),
        num_classes: int = NUM_CLASSES,
        pe_freqs: int = 6,
        grid: Sequence[int] = GRID_SHAPE,
        refine: bool = True,
        bev: bool = False,
        backend: str = "fused",
    ):
        super().__init__()
        if not refine and feature_channels != in_channels:
            raise ValueError(
                f"feature_channels ({feature_channels}) must equal in_channels ({in_channels}) without refinement"
            )
        if backend not in ("fused", "reference"):
            raise ValueError(f"backend must be 'fused' or 'reference', got {backend!r}")
        if not 0 <= pe_freqs <= MAX_PE_FREQS:  # the fused op's limit, checked here rather than at the first forward
            raise ValueError(f"pe_freqs must be in [0, {MAX_PE_FREQS}], got {pe_freqs}")
        if not 1 <= num_classes <= 256:  # argmax labels are uint8
            raise ValueError(f"num_classes must be in [1, 256], got {num_classes}")
        self.grid = tuple(int(n) for n in grid)
        self.pe_freqs = pe_freqs
        self.bev = bev
        self.backend = backend
        self.feature_channels = feature_channels
        planes = 1 if bev else 3
        self.refiners = nn.ModuleList(
            PlaneRefiner(in_channels, feature_channels) if refine else nn.Identity() for _ in range(planes)
        )
        widths = [feature_channels + 6 * pe_freqs, *hidden, num_classes]
        self.mlp = nn.ModuleList(nn.Linear(i, o) for i, o in zip(widths[:-1], widths[1:]))

    @classmethod
    def from_config(cls, config: AutoencoderConfig, **overrides) -> TriplaneDecoder:
        """The decoder of a named autoencoder config."""
        kwargs = dict(
            in_channels=config.channels,
            feature_channels=config.decoder_channels,
            hidden=config.decoder_hidden,
            num_classes=config.num_classes,
            pe_freqs=config.pe_freqs,
            grid=config.grid,
            refine=config.refine,
            bev=config.latent == "bev",
        )
        kwargs.update(overrides)
        return cls(**kwargs)

    def features(self, triplane: Triplane | Sequence[Tensor]) -> Triplane:
        """The refined planes fed to the decode op (zero vertical planes for a BEV latent)."""
        if not self.bev and (triplane[1] is None or triplane[2] is None):
            raise ValueError("a BEV-only latent (xz and yz are None) given to a triplane decoder; "
                             "decode it with a decoder built with bev=True")
        xy = self.refiners[0](triplane[0])
        if self.bev:
            b, c, x, y = xy.shape
            # one-cell vertical planes of zeros: the lookup adds nothing, height comes from PE
            return Triplane(xy, xy.new_zeros(b, c, x, 1), xy.new_zeros(b, c, y, 1))
        return Triplane(xy, self.refiners[1](triplane[1]), self.refiners[2](triplane[2]))

    def _decode(self, triplane, points: Tensor | None, argmax: bool, live: Tensor | None = None) -> Tensor:
        # under autocast the refiners may return a lower precision than the MLP's weights
        dtype = self.mlp[0].weight.dtype
        planes = self.features(triplane).map(lambda p: p.to(dtype))
        weights = [layer.weight for layer in self.mlp]
        biases = [layer.bias for layer in self.mlp]
        op = (fused_ops if self.backend == "fused" else reference_ops).triplane_decode
        query = {"grid": self.grid} if points is None else {"points": points.to(dtype)}
        if live is not None:
            query["live"] = live
        return op(*planes, weights, biases, pe_freqs=self.pe_freqs, argmax=argmax, **query)

    def forward(self, triplane: Triplane | Sequence[Tensor], points: Tensor | None = None) -> Tensor:
        """Class logits ``[B, X, Y, Z, K]`` of the full grid, or ``[B, N, K]`` of ``points``
        ``[B, N, 3]`` (x, y, z in [-1, 1]; voxel centres are ``(2 i + 1) / N - 1``)."""
        return self._decode(triplane, points, argmax=False)

    @torch.no_grad()
    def predict(self, triplane: Triplane | Sequence[Tensor], points: Tensor | None = None,
                live: Tensor | None = None) -> Tensor:
        """uint8 class labels ``[B, X, Y, Z]`` (or ``[B, N]``) through the argmax mode: no
        logits tensor is allocated. ``live`` int64 ``[B]``: decode only each element's first
        ``live[b]`` points (label 0 beyond; see :func:`t3fast.ops.triplane_decode`)."""
        return self._decode(triplane, points, argmax=True, live=live)
