"""DeltaTriplaneForecaster (Phi_fut): predicts how each plane of the triplane changes.

One :class:`PlanePredictor` per plane, with separate weights. A predictor encodes each of the
``history`` past planes with a UNet-style encoder into V scales; at every scale a Transformer
encoder turns the history tokens into a memory, and a Transformer decoder whose learnable
future queries (one set per future step) cross-attend to it yields that scale's token change;
UNet-style upsampling fuses the per-scale changes into the plane change Delta, and the next
plane is ``delta_fuse(Delta, prev)`` (a 1x1 convolution of the previous plane plus Delta).

Attention per scale: full spatio-temporal attention over all ``T * h * w`` tokens costs
``(T h w)^2``; at the xy plane's finest scale (T = 5, 100 x 100) that is 2.5e9 scores per head,
far too many. A scale therefore uses full attention when ``T * h * w <= max_tokens`` (the
coarse scales, where objects' displacements span few cells and global context matters) and
temporal attention otherwise (each location attends over its own history: tokens ``T``,
cost ``h w T^2``). Below the finest scale each location's query also attends to its
neighbourhood in the last frames (:class:`LocalAttention`), so content that moves with the
ego can be moved sharply instead of being rebuilt from the coarse scales.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from t3fast.device_constants import made_once
from t3fast.models.attention import TransformerStack
from t3fast.models.blocks import group_norm
from t3fast.models.triplane import Triplane
from t3fast.models.weight_uses import call_with, weights_per_use
from t3fast.ops import delta_fuse


@made_once
def _sinusoid_2d(h: int, w: int, dim: int, device: torch.device) -> Tensor:
    """Fixed 2D sin/cos position code ``[h * w, dim]`` (dim divisible by 4); made once per
    size and device (read-only), not at every step of every rollout."""
    quarter = dim // 4
    freq = torch.exp(torch.arange(quarter, device=device) * (-math.log(10000.0) / max(quarter, 1)))
    ys, xs = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    ay, ax = ys.flatten()[:, None] * freq, xs.flatten()[:, None] * freq
    return torch.cat([ay.sin(), ay.cos(), ax.sin(), ax.cos()], dim=1)


LOCAL_FRAMES = 2  # history frames the neighbourhood attention reads (motion needs two)


class LocalAttention(nn.Module):
    """Neighbourhood attention: the query of each location ``[B, D, h, w]`` attends to the
    ``(2 radius + 1)^2`` neighbours of that location in each of ``frames`` maps
    ``[B, frames, D, h, w]``; keys carry a learned embedding of their frame and offset.
    Keys and values are projected before the neighbourhoods are gathered (one ``unfold``
    each), and scores are formed in the unfolded layout, with no token copies."""

    def __init__(self, dim: int, heads: int, radius: int, frames: int):
        super().__init__()
        self.heads, self.radius = heads, radius
        self.norm = nn.GroupNorm(1, dim)
        self.q, self.k, self.v, self.out = (nn.Conv2d(dim, dim, 1) for _ in range(4))
        self.offsets = nn.Parameter(torch.randn(frames, dim, (2 * radius + 1) ** 2) * 0.02)
        nn.init.zeros_(self.out.weight)  # starts as "no contribution"
        nn.init.zeros_(self.out.bias)

    def _gather(self, x: Tensor, b: int, t: int) -> Tensor:
        d, h, w = x.shape[-3:]
        k = 2 * self.radius + 1
        return F.unfold(x, k, padding=self.radius).view(b, t, d, k * k, h * w)

    def forward(self, query: Tensor, maps: Tensor) -> Tensor:
        b, t, d, h, w = maps.shape
        heads, dh = self.heads, d // self.heads
        flat = self.norm(maps.flatten(0, 1))
        keys = self._gather(self.k(flat), b, t) + self.offsets[-t:, :, :, None]  # [B, T, D, K, hw]
        values = self._gather(self.v(flat), b, t)
        q = self.q(query).view(b, 1, heads, dh, 1, h * w) / math.sqrt(dh)
        scores = (keys.view(b, t, heads, dh, -1, h * w) * q).sum(3)  # [B, T, heads, K, hw]
        attn = scores.permute(0, 2, 1, 3, 4).reshape(b, heads, -1, h * w).softmax(dim=2)
        attn = attn.view(b, heads, t, 1, -1, h * w).transpose(1, 2)  # [B, T, heads, 1, K, hw]
        out = (values.view(b, t, heads, dh, -1, h * w) * attn).sum((1, 4))  # [B, heads, dh, hw]
        return self.out(out.reshape(b, d, h, w))


class ScaleTransformer(nn.Module):
    """History tokens of one scale -> that scale's token change for future step ``k``.

    Input ``[B, T, D, h, w]``, output ``[B, D, h, w]``. ``full_attention``: one sequence of all
    ``T h w`` tokens. Otherwise the encoder attends over each location's own ``T`` frames and
    each location's query (the step's learnable query plus its newest memory token) attends to
    that memory; with ``local`` the query also attends to the ``(2 radius + 1)^2``
    neighbourhood of the location in the last ``LOCAL_FRAMES`` frames, so content can move up
    to ``radius`` cells per scale and step.
    """

    def __init__(
        self, dim: int, history: int, steps: int, heads: int, layers: int, full_attention: bool,
        local: bool = True, radius: int = 3,
    ):
        super().__init__()
        self.full_attention = full_attention
        self.time = nn.Parameter(torch.zeros(history, dim))  # which past frame a token comes from
        self.queries = nn.Parameter(torch.zeros(steps, dim))  # learnable future query per step
        nn.init.normal_(self.time, std=0.02)
        nn.init.normal_(self.queries, std=0.02)
        self.encoder = TransformerStack(dim, heads, layers)
        self.decoder = TransformerStack(dim, heads, layers, cross=True)
        self.local = LocalAttention(dim, heads, radius, LOCAL_FRAMES) if local and not full_attention else None

    def forward(self, x: Tensor, step: int) -> Tensor:
        b, t, d, h, w = x.shape
        tokens = x.permute(0, 3, 4, 1, 2) + self.time[-t:]  # [B, h, w, T, D]
        query = self.queries[step]
        if self.full_attention:
            space = _sinusoid_2d(h, w, d, x.device).view(h, w, 1, d)
            memory = self.encoder((tokens + space).reshape(b, h * w * t, d))
            q = (query + space.view(h * w, d)).expand(b, h * w, d)
            return self.decoder(q, memory).transpose(1, 2).reshape(b, d, h, w)
        memory = self.encoder(tokens.reshape(b * h * w, t, d))  # [B h w, T, D]
        q = (query + memory[:, -1]).unsqueeze(1)
        out = self.decoder(q, memory).view(b, h, w, d).permute(0, 3, 1, 2)
        if self.local is not None:  # content moves: gather from the neighbourhood in the last frames
            grid = memory.view(b, h, w, t, d)[:, :, :, -LOCAL_FRAMES:].permute(0, 3, 4, 1, 2)
            out = out + self.local(q.view(b, h, w, d).permute(0, 3, 1, 2), grid)
        # contiguous NCHW: a permuted (channels-last) layout otherwise propagates into the
        # planner's convs, whose oneDNN weight gradient then aborted with heap corruption
        # (torch 2.13 CPU; regression test in tests/models/test_world_model.py)
        return out.contiguous()


class PlanePredictor(nn.Module):
    """Phi_fut of one plane: history ``[B, T, C, H, W]`` -> change Delta ``[B, C, H, W]``."""

    def __init__(
        self,
        channels: int,
        plane_size: tuple[int, int],
        widths: Sequence[int],
        history: int,
        steps: int,
        heads: int,
        layers: int,
        max_tokens: int,
    ):
        super().__init__()
        self.down = nn.ModuleList()
        self.scales = nn.ModuleList()
        h, w = plane_size
        prev = channels
        for v, width in enumerate(widths):
            stride = 1 if v == 0 else 2
            self.down.append(
                nn.Sequential(nn.Conv2d(prev, width, 3, stride=stride, padding=1), group_norm(width), nn.SiLU())
            )
            if v:
                h, w = (h + 1) // 2, (w + 1) // 2
            full = history * h * w <= max_tokens
            # neighbourhood attention below the finest scale: at the second scale a radius of
            # 3 cells spans 6 plane cells (~5 m), one step of ego motion at ~10 m/s
            self.scales.append(ScaleTransformer(width, history, steps, heads, layers, full, local=v > 0))
            prev = width
        self.up = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(widths[v + 1] + widths[v], widths[v], 3, padding=1), group_norm(widths[v]), nn.SiLU()
            )
            for v in range(len(widths) - 1)
        )
        self.head = nn.Conv2d(widths[0], channels, 1)
        nn.init.zeros_(self.head.weight)  # start from "no change"
        nn.init.zeros_(self.head.bias)

    def forward(self, history: Tensor, step: int) -> Tensor:
        b, t = history.shape[:2]
        x = history.flatten(0, 1)
        changes = []
        for down, scale in zip(self.down, self.scales):
            x = down(x)
            changes.append(scale(x.unflatten(0, (b, t)), step))
        y = changes[-1]
        for v in range(len(changes) - 2, -1, -1):
            y = F.interpolate(y, size=changes[v].shape[-2:], mode="bilinear", align_corners=False)
            y = self.up[v](torch.cat([y, changes[v]], dim=1))
        return self.head(y)


class DeltaTriplaneForecaster(nn.Module):
    """Autoregressive forecaster of future triplanes.

    Args:
        channels: triplane channels C.
        plane_shape: ``(X', Y', Z')``.
        widths: channels of the V scales (V = len(widths); the papers use V = 5).
        history: past frames the predictors see (the present included).
        steps: future steps the learnable queries are made for.
        predict_delta: ``next = delta_fuse(Delta, prev)``; False predicts the full next plane
            (the papers' "w/o triplane changes" ablation).
        bev: forecast only the xy plane (BEV-only latent).
    """

    def __init__(
        self,
        channels: int = 8,
        plane_shape: tuple[int, int, int] = (100, 100, 16),
        widths: Sequence[int] = (32, 48, 64, 96, 128),
        history: int = 5,
        steps: int = 6,
        heads: int = 4,
        layers: int = 1,
        max_tokens: int = 1024,
        predict_delta: bool = True,
        bev: bool = False,
    ):
        super().__init__()
        x, y, z = plane_shape
        sizes = {"xy": (x, y)} if bev else {"xy": (x, y), "xz": (x, z), "yz": (y, z)}
        self.history, self.steps, self.predict_delta = history, steps, predict_delta
        self.predictors = nn.ModuleDict(
            {
                name: PlanePredictor(channels, size, widths, history, steps, heads, layers, max_tokens)
                for name, size in sizes.items()
            }
        )
        # the 1x1 fusion of delta_fuse is the identity plus a learned part that starts at 0, so
        # weight decay pulls it toward "keep the previous plane", not toward erasing it
        self.fuse_residual = nn.ParameterDict({n: nn.Parameter(torch.zeros(channels, channels)) for n in sizes})
        self.fuse_bias = nn.ParameterDict({n: nn.Parameter(torch.zeros(channels)) for n in sizes})

    def fuse_weight(self, name: str) -> Tensor:
        """The 1x1 fusion weight ``[C, C]`` of plane ``name``: identity + learned part."""
        residual = self.fuse_residual[name]
        return torch.eye(residual.shape[0], dtype=residual.dtype, device=residual.device) + residual

    def upgrade_state_dict(self, state_dict: dict, prefix: str = "") -> None:
        """Renames, in place, the weights of checkpoints written before the identity + residual
        parametrisation, which store the full fusion weight (a square matrix)."""
        for name in list(self.fuse_residual):
            old = state_dict.get(f"{prefix}fuse_weight.{name}")
            if isinstance(old, Tensor) and old.dim() == 2 and old.shape[0] == old.shape[1]:
                del state_dict[f"{prefix}fuse_weight.{name}"]
                state_dict[f"{prefix}fuse_residual.{name}"] = old - torch.eye(old.shape[0], dtype=old.dtype)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        self.upgrade_state_dict(state_dict, prefix)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def step(self, history: Triplane, step: int,
             weights: dict[str, dict[str, Tensor] | None] | None = None) -> tuple[Triplane, Triplane]:
        """One step: history planes ``[B, T, C, H, W]`` -> (next triplane, its change Delta).
        ``weights``: per plane, this step's aliases of its predictor's weights
        (:func:`~t3fast.models.weight_uses.weights_per_use`), else the predictors' own."""
        nxt, deltas = [], []
        for name, planes in zip(("xy", "xz", "yz"), history):
            if name not in self.predictors:
                nxt.append(None)
                deltas.append(None)
                continue
            predictor = self.predictors[name]
            delta = call_with(predictor, None if weights is None else weights[name], planes[:, -self.history :], step)
            prev = planes[:, -1]
            out = delta_fuse(delta, prev, self.fuse_weight(name), self.fuse_bias[name]) if self.predict_delta else delta
            nxt.append(out)
            deltas.append(out - prev if not self.predict_delta else delta)
        return Triplane(*nxt), Triplane(*deltas)

    def forward(
        self, past: Triplane, steps: int | None = None, first_step: int = 0
    ) -> tuple[list[Triplane], list[Triplane]]:
        """Past planes ``[B, T, C, H, W]`` -> ``steps`` future triplanes and their changes; each
        prediction is appended to the history of the next step. ``first_step`` is the future
        step the first prediction is (training starts rollouts from encoded later frames)."""
        history = past
        futures, deltas = [], []
        ks = range(first_step, first_step + (steps or self.steps))
        # every step reuses the predictors: their gradients summed in one pass (see weight_uses)
        uses = {name: weights_per_use(predictor, len(ks)) for name, predictor in self.predictors.items()}
        for i, k in enumerate(ks):
            nxt, delta = self.step(history, min(k, self.steps - 1), {name: u[i] for name, u in uses.items()})
            futures.append(nxt)
            deltas.append(delta)
            history = history.append(nxt)
        return futures, deltas
