"""MotionPlanner (Phi_act): the ego's next displacements from triplanes and past actions.

Per future step: ResNet-18-style encoders map the previous triplane, the change Delta and the
next triplane into a shared latent (z_p, dz, z_f); two FC + sigmoid gates computed from dz
select the motion-related parts of z_p and z_f; the gated features and dz are averaged, passed
through an FC layer and added to a learnable future query, giving Q_a (d_act = 50). The past
actions, projected to d_act, go through a Transformer encoder; a Transformer decoder with Q_a
cross-attends to them and predicts the next displacement (dx, dy), which is appended to the
actions for the next step.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from t3fast.models.blocks import group_norm
from t3fast.models.ego_motion import rotate
from t3fast.models.triplane import Triplane
from t3fast.models.weight_uses import call_with, weights_per_use


class BasicBlock(nn.Module):
    """ResNet basic block (two 3x3 convs, projection shortcut when the shape changes)."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(cin, cout, 3, stride, 1, bias=False),
            group_norm(cout),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, 1, 1, bias=False),
            group_norm(cout),
        )
        self.short = (
            nn.Identity()
            if stride == 1 and cin == cout
            else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), group_norm(cout))
        )

    def forward(self, x: Tensor) -> Tensor:
        return torch.relu(self.body(x) + self.short(x))


class PlaneResNet(nn.Module):
    """ResNet-18 layout (stem, 4 stages of 2 basic blocks, global pool): ``[B, C, H, W] -> [B, widths[-1]]``."""

    def __init__(self, channels: int, widths: Sequence[int]):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(channels, widths[0], 3, 1, 1, bias=False), group_norm(widths[0]), nn.ReLU())
        blocks, prev = [], widths[0]
        for i, width in enumerate(widths):
            blocks += [BasicBlock(prev, width, 1 if i == 0 else 2), BasicBlock(width, width, 1)]
            prev = width
        self.blocks = nn.Sequential(*blocks)

    def forward(self, x: Tensor) -> Tensor:
        return self.blocks(self.stem(x)).mean(dim=(2, 3))


class TriplaneResNet(nn.Module):
    """A triplane -> one vector ``[B, d]``: one PlaneResNet shared by the planes (convolutions
    do not care about the plane's size; sharing keeps three encoders at ResNet-18 size each),
    pooled features concatenated in plane order, then FC."""

    def __init__(self, channels: int, widths: Sequence[int], out_dim: int, planes: int):
        super().__init__()
        self.net = PlaneResNet(channels, widths)
        self.fc = nn.Linear(planes * widths[-1], out_dim)

    def forward(self, triplane: Triplane) -> Tensor:
        planes = [p for p in triplane if p is not None]
        uses = weights_per_use(self.net, len(planes))
        return self.fc(torch.cat([call_with(self.net, w, p) for w, p in zip(uses, planes)], dim=1))


def _turn(prev: Tensor, last: Tensor, min_step: float) -> Tensor:
    """The angle ``[B]`` from displacement ``prev`` to ``last`` ``[B, 2]``; 0 where either is
    shorter than ``min_step`` metres (a heading there is noise)."""
    turn = torch.atan2(prev[:, 0] * last[:, 1] - prev[:, 1] * last[:, 0], (prev * last).sum(-1))
    moving = (last.norm(dim=-1) > min_step) & (prev.norm(dim=-1) > min_step)
    return torch.where(moving, turn, torch.zeros_like(turn))


def continue_motion(actions: Tensor, min_step: float = 0.2) -> Tensor:
    """The next displacement ``[B, 2]`` at constant speed and turn rate: the last displacement of
    ``actions`` ``[B, T, 2]`` turned by the angle between the last two (an arc, as the ego
    drives through a bend). Below ``min_step`` metres per step a heading is noise, so the
    last displacement is kept as it is."""
    last = actions[:, -1]
    if actions.shape[1] < 2:
        return last
    return rotate(last, _turn(actions[:, -2], last, min_step))


def constant_turn_rate(past_actions: Tensor, steps: int = 6, min_step: float = 0.2) -> Tensor:
    """Constant speed and turn rate: each displacement is the previous one turned by the angle
    between the last two past ones (the untrained planner's plan), :func:`continue_motion`
    applied ``steps`` times, in closed form: the k-th is the last past one turned k times.
    ``[B, T, 2] -> [B, steps, 2]``."""
    last = past_actions[:, -1]
    if past_actions.shape[1] < 2:
        return last.unsqueeze(1).expand(-1, steps, -1).clone()
    turn = _turn(past_actions[:, -2], last, min_step)
    k = torch.arange(1, steps + 1, device=last.device, dtype=last.dtype)
    return rotate(last.unsqueeze(1), turn.unsqueeze(1) * k)


class MotionPlanner(nn.Module):
    """Args:
        channels: triplane channels C.
        widths: stage widths of the ResNet-18-style encoders (ResNet-18: 64, 128, 256, 512).
        d_act: token width of the action Transformer (the papers: 50).
        steps: future steps (learnable future queries).
        past: number of past actions.
        heads, layers: of the action Transformer encoder and decoder.
        bev: triplanes carry only the xy plane.
    """

    def __init__(
        self,
        channels: int = 8,
        widths: Sequence[int] = (64, 128, 256, 512),
        d_act: int = 50,
        steps: int = 6,
        past: int = 4,
        heads: int = 5,
        layers: int = 2,
        bev: bool = False,
    ):
        super().__init__()
        planes = 1 if bev else 3
        self.enc_prev, self.enc_delta, self.enc_next = (
            TriplaneResNet(channels, widths, d_act, planes) for _ in range(3)
        )
        self.gate_prev = nn.Sequential(nn.Linear(d_act, d_act), nn.Sigmoid())
        self.gate_next = nn.Sequential(nn.Linear(d_act, d_act), nn.Sigmoid())
        self.fc = nn.Linear(d_act, d_act)
        self.future_queries = nn.Parameter(torch.randn(steps, d_act) * 0.02)
        self.action_in = nn.Linear(2, d_act)
        self.action_time = nn.Parameter(torch.randn(past + steps, d_act) * 0.02)
        enc = nn.TransformerEncoderLayer(d_act, heads, 4 * d_act, dropout=0.0, batch_first=True, norm_first=True)
        dec = nn.TransformerDecoderLayer(d_act, heads, 4 * d_act, dropout=0.0, batch_first=True, norm_first=True)
        self.encoder = nn.TransformerEncoder(enc, layers, enable_nested_tensor=False)
        self.decoder = nn.TransformerDecoder(dec, layers)
        self.action_out = nn.Linear(d_act, 2)
        nn.init.zeros_(self.action_out.weight)
        nn.init.zeros_(self.action_out.bias)
        self.steps = steps

    def queries(self, prevs: Sequence[Triplane], deltas: Sequence[Triplane], nexts: Sequence[Triplane],
                first_step: int) -> Tensor:
        """Q_a ``[S, B, d_act]`` of the S future steps from ``first_step`` on, from each step's
        (previous, change, next) triplanes: the steps' triplanes go through each encoder together
        (they do not depend on the actions, which are planned one step after another)."""
        z_p, dz, z_f = (enc(Triplane.cat(ts)) for enc, ts in ((self.enc_prev, prevs), (self.enc_delta, deltas),
                                                             (self.enc_next, nexts)))
        fused = (self.gate_prev(dz) * z_p + dz + self.gate_next(dz) * z_f) / 3
        # each step's learnable query (the last one's past the last): an index made on the device
        steps = torch.arange(first_step, first_step + len(nexts), device=fused.device).clamp(max=self.steps - 1)
        return self.fc(fused).view(len(nexts), -1, fused.shape[-1]) + self.future_queries[steps, None]

    def next_action(self, q_a: Tensor, actions: Tensor, weights: tuple[dict | None, dict | None] = (None, None)
                    ) -> Tensor:
        """Displacement ``[B, 2]`` from Q_a and the actions so far ``[B, T, 2]``: the observed
        motion continued (:func:`continue_motion`) plus the decoder's correction (zero at
        initialisation, so an untrained planner drives on at constant speed and turn rate and
        training learns how motion changes). ``weights``: this step's aliases of the action
        encoder's and decoder's weights (:func:`~t3fast.models.weight_uses.weights_per_use`)."""
        tokens = self.action_in(actions) + self.action_time[: actions.shape[1]]
        memory = call_with(self.encoder, weights[0], tokens)
        correction = self.action_out(call_with(self.decoder, weights[1], q_a.unsqueeze(1), memory)[:, 0])
        return continue_motion(actions) + correction

    def forward(
        self,
        present: Triplane,
        futures: Sequence[Triplane],
        deltas: Sequence[Triplane],
        past_actions: Tensor,
        first_step: int = 0,
    ) -> Tensor:
        """Future displacements ``[B, S, 2]`` for S = len(futures) steps, autoregressively.

        Args:
            present: the triplane before the first future one (planes ``[B, C, H, W]``).
            futures, deltas: per future step, the (predicted) triplane and its change.
            past_actions: ``[B, T_p + first_step, 2]`` displacements so far, in the present frame.
            first_step: the future step of ``futures[0]``.
        """
        if not futures:
            return past_actions.new_zeros(past_actions.shape[0], 0, 2)
        actions, out = past_actions, []
        # every step reuses the action Transformer: its gradients summed in one pass (see weight_uses)
        uses = zip(weights_per_use(self.encoder, len(futures)), weights_per_use(self.decoder, len(futures)))
        for q_a, weights in zip(self.queries([present, *futures[:-1]], deltas, futures, first_step), uses):
            a = self.next_action(q_a, actions, weights)
            out.append(a)
            actions = torch.cat([actions, a.unsqueeze(1)], dim=1)
        return torch.stack(out, dim=1)
