"""Stage 6: the future frames as labels uint8 ``[B, S, X, Y, Z]``, each in the ego frame of its pose.

Three renderers, one per kind of model (chosen by :mod:`t3fast.forecast.pipeline`):

* :class:`DecodeFrames`: every frame decoded from its forecast triplane (the papers'
  formulation, and ego-aligned models without the observed present);
* :class:`KeepObservedStatic`: the observed present moved with the ego, edited where the
  forecast changes an agent (:func:`observed_static`), decoding only the voxels that can change;
* :class:`DrawAgents`: the observed present with its agents moved in label space as
  :mod:`t3fast.forecast.motion` says, drawn exactly (no decoding blurs a car or loses a pedestrian).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from t3fast.agents.boxes import draw_agent_boxes
from t3fast.agents.tracker import move_agents
from t3fast.data.classes import AGENT_CLASSES, FLAT_GROUND_CLASSES, FREE, IGNORE, in_classes
from t3fast.forecast.records import AgentMoves, Past, Scene
from t3fast.host_syncs import reads_host
from t3fast.models.decoder import TriplaneDecoder
from t3fast.models.ego_motion import column_queries, frame_queries, unwarp_sequence, voxel_queries
from t3fast.models.triplane import Triplane


def present_in_frames(present: Tensor, poses: Tensor) -> Tensor:
    """The present frame's labels ``[B, X, Y, Z]`` moved into the ego frame of each future pose
    ``poses`` ``[B, S, 3]``: ``[B, S, X, Y, Z]``, ``IGNORE`` where a frame looks beyond the
    present grid."""
    return unwarp_sequence(present.unsqueeze(1).expand(-1, poses.shape[1], *present.shape[1:]), poses, fill=IGNORE)


def observed_static(decoded: Tensor, reference: Tensor, moved: Tensor) -> Tensor:
    """Future frames as the observed present edited where the forecast moves agents.

    The static world does not change in 3 s, and the latent loses detail (thin walls, trunks,
    small cars), so each future frame starts from the present frame's labels moved into its
    ego frame, ``moved`` ``[B, S, X, Y, Z]`` (:func:`present_in_frames`). The forecast
    ``decoded`` ``[B, S, X, Y, Z]`` edits it only where it differs from ``reference`` (the present
    triplane decoded at the same voxels: what the latent shows with no change), the change
    involves an agent class (vehicles and humans move), and the observed voxel is free or an
    agent (agents do not move into walls or the ground). With no predicted change the result is
    the present frame moved with the ego, exactly. Beyond the present grid nothing was
    observed: there the forecast's continuation of its edge is kept for flat ground (roads and
    sidewalks go on) and everything else is free (continuing walls, trees and cars past the
    edge cost 6.5 IoU points on validation windows; ground alone gained 1.6).
    """
    agent_change = (decoded != reference) & (in_classes(decoded, AGENT_CLASSES) | in_classes(reference, AGENT_CLASSES))
    editable = in_classes(moved, AGENT_CLASSES) | (moved == FREE)
    inside = torch.where(agent_change & editable, decoded, moved)
    return torch.where(moved == IGNORE, beyond_present(decoded), inside)


def front_slots(mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The True entries of ``mask`` ``[B, N]`` gathered, in order, to the front of a buffer of
    N, all on the device (no host read): each entry's place ``slot`` ``[B, N]`` (N for a False
    one), the entry at each place ``index`` ``[B, N]`` (0 past the filled part) and the filled
    length ``count`` ``[B]``."""
    n = mask.shape[1]
    slot = torch.where(mask, mask.cumsum(1) - 1, n)
    index = torch.zeros(mask.shape[0], n + 1, dtype=torch.long, device=mask.device)
    index.scatter_(1, slot, torch.arange(n, device=mask.device).expand_as(slot))
    return slot, index[:, :n], mask.sum(1)


def decode_where(decoder: TriplaneDecoder, planes: Triplane, points: Tensor, mask: Tensor) -> Tensor:
    """``decoder.predict(planes, points)`` (``points`` ``[B, N, 3]``) where ``mask`` ``[B, N]``
    holds, decoding those points only (:func:`front_slots`, ``live``); 0 elsewhere."""
    slot, index, count = front_slots(mask)
    buffer = points.gather(1, index[..., None].expand(-1, -1, points.shape[-1]))
    return decoder.predict(planes, buffer, live=count).gather(1, slot.clamp(max=mask.shape[1] - 1))


def beyond_present(decoded: Tensor) -> Tensor:
    """What a forecast shows beyond the observed present grid: its decoded flat ground (roads
    and sidewalks go on), everything else free."""
    return torch.where(in_classes(decoded, FLAT_GROUND_CLASSES), decoded, FREE)


class DecodeFrames:
    """Each future triplane decoded: at the voxels of the ego frame of its pose (``ego_aligned``)
    or, for a model whose every frame is in its own ego frame, at its own grid."""

    def __init__(self, decoder: TriplaneDecoder, ego_aligned: bool):
        self.decoder, self.ego_aligned = decoder, ego_aligned

    @torch.no_grad()
    def __call__(self, past: Past, scene: Scene, moves: list[AgentMoves] | None, poses: Tensor) -> Tensor:
        if not self.ego_aligned:
            return torch.stack([self.decoder.predict(t) for t in scene.futures], dim=1)
        grid = self.decoder.grid
        frames = []
        for k, t in enumerate(scene.futures):
            points = frame_queries(poses[:, k].float(), grid)
            frames.append(self.decoder.predict(t, points).view(-1, *grid))
        return torch.stack(frames, dim=1)


class KeepObservedStatic:
    """The observed present edited by the forecast (:func:`observed_static`), decoding only the
    voxels whose labels can differ from the present's. Where a future triplane's refined planes
    (what the decode op looks up) equal the present one's at every cell a voxel's lookup reads
    (the xy cells around its column; xz and yz whole), the forecast decodes to exactly what the
    present triplane does, so :func:`observed_static` keeps the observed label there. Only the
    voxels near changed xy cells and those beyond the present grid are decoded; a forecaster that
    moves a few agents and carries xz/yz (the flow forecaster) decodes a few percent of each
    frame. Same labels as decoding every voxel. Where the host may not read
    (:func:`~t3fast.host_syncs.reads_host`), those voxels are decoded from a buffer whose length
    stays on the device (:func:`decode_where`)."""

    def __init__(self, decoder: TriplaneDecoder):
        self.decoder = decoder

    @torch.no_grad()
    def __call__(self, past: Past, scene: Scene, moves: list[AgentMoves] | None, poses: Tensor) -> Tensor:
        present_planes = past.present_planes
        moved = present_in_frames(past.present_labels, poses)
        labels = moved.clone()
        b = moved.shape[0]
        h, w = present_planes.xy.shape[-2:]
        now = self.decoder.features(present_planes)  # what the lookups read: the refined planes
        compact = reads_host(moved.device)
        for k, future in enumerate(scene.futures):
            points = frame_queries(poses[:, k].float(), self.decoder.grid)  # [B, N, 3], normalised
            i = ((points[..., 0] + 1) * h / 2 - 0.5).round().long().clamp(0, h - 1)
            j = ((points[..., 1] + 1) * w / 2 - 0.5).round().long().clamp(0, w - 1)
            observed = moved[:, k].reshape(b, -1)
            need = self._changed_cells(future, now, compact).flatten(1).gather(1, i * w + j) | (observed == IGNORE)
            if not compact:
                decoded = decode_where(self.decoder, future, points, need)
                agents = need & (in_classes(decoded, AGENT_CLASSES) | in_classes(observed, AGENT_CLASSES))
                reference = torch.where(agents, decode_where(self.decoder, present_planes, points, agents), decoded)
                edited = torch.where(need, observed_static(decoded, reference, observed), observed)
                labels[:, k] = edited.view_as(labels[:, k])
                continue
            for n in range(b):
                index = need[n].nonzero().squeeze(1)
                if not index.numel():
                    continue
                query = points[n : n + 1, index]
                decoded = self.decoder.predict(future.map(lambda p, n=n: p[n : n + 1]), query).view(-1)
                reference = self._present_where_agents(present_planes.map(lambda p, n=n: p[n : n + 1]), query,
                                                       decoded, observed[n, index])
                labels[n, k].view(-1)[index] = observed_static(decoded, reference, observed[n, index])
        return labels

    def _changed_cells(self, future: Triplane, now: Triplane, compact: bool) -> Tensor:
        """``[B, H, W]``: the xy cells whose lookups can read a refined plane of ``future`` that
        differs from the present's ``now`` (every cell where xz or yz changed: decided on the
        host when ``compact``, else on the device)."""
        refined = self.decoder.features(future)
        b, _, h, w = now.xy.shape
        if compact and not (torch.equal(refined.xz, now.xz) and torch.equal(refined.yz, now.yz)):
            return torch.ones(b, h, w, dtype=torch.bool, device=now.xy.device)  # xz/yz changed: every voxel
        # a lookup reads the 2 x 2 cells around its point: the nearest one's 3 x 3 neighbourhood covers them
        diff = (refined.xy != now.xy).any(1, keepdim=True).float()
        cells = nn.functional.max_pool2d(diff, 3, stride=1, padding=1)[:, 0] > 0
        if compact:
            return cells
        vertical = [(r != p).flatten(1).any(1) for r, p in zip(refined[1:], now[1:]) if p is not None]
        return cells | torch.stack(vertical).any(0)[:, None, None] if vertical else cells

    def _present_where_agents(self, planes: Triplane, points: Tensor, decoded: Tensor, observed: Tensor) -> Tensor:
        """The reference of :func:`observed_static` for one frame's voxels: their forecast labels
        ``decoded`` ``[N]``, except where those or the observed labels ``observed`` ``[N]`` show an
        agent, where the present triplane ``planes`` (batch 1) is decoded at ``points``
        ``[1, N, 3]`` instead."""
        need = in_classes(decoded, AGENT_CLASSES) | in_classes(observed, AGENT_CLASSES)
        reference = decoded.clone()
        if bool(need.any()):
            reference[need] = self.decoder.predict(planes, points[:, need]).view(-1)
        return reference


class DrawAgents:
    """The observed present with each agent moved as a whole (:class:`AgentMoves`) and taken
    into the frame's pose; beyond the present grid, the forecast's decoded flat ground
    (:func:`beyond_present`). The forecaster's motion is drawn exactly (the latent render lost
    1.1 moving-class mIoU to the tracker that moves the same agents this way); the agents with a
    trusted fitted box are drawn as their box, not rounded to cells (:mod:`t3fast.agents.boxes`)."""

    def __init__(self, decoder: TriplaneDecoder):
        self.decoder = decoder

    @torch.no_grad()
    def __call__(self, past: Past, scene: Scene, moves: list[AgentMoves] | None, poses: Tensor) -> Tensor:
        present = past.present_labels
        if reads_host(present.device):  # each window's agents, counted on the host
            scenes = torch.stack([move_agents(present[n], move.agents, move.shift.round().long(), FREE,
                                              keep=~move.as_box.to(present.device)) for n, move in enumerate(moves)])
        else:  # in fixed slots: every window at once
            agents = {k: v if k == "columns" else torch.stack([m.agents[k] for m in moves])
                      for k, v in moves[0].agents.items()}
            shift = torch.stack([m.shift for m in moves]).round().long()
            scenes = move_agents(present, agents, shift, FREE, keep=~torch.stack([m.as_box for m in moves]))
        labels = unwarp_sequence(scenes, poses, fill=IGNORE)  # the agents drawn as boxes left their voxels
        self._fill_unseen(labels, scene.futures, poses)
        if reads_host(present.device):  # each window's boxes, as many as it has
            for n, move in enumerate(moves):
                if move.box_poses is not None:
                    self._draw_boxes(labels[n], move.box_poses, move.as_box,
                                     *(getattr(move.boxes, k) for k in self.BOX_FIELDS), poses[n])
        elif moves[0].box_poses is not None:  # in fixed slots: every window's boxes in one call
            fields = (torch.stack([getattr(m.boxes, k) for m in moves]) for k in self.BOX_FIELDS)
            self._draw_boxes(labels, torch.stack([m.box_poses for m in moves]), torch.stack([m.as_box for m in moves]),
                             *fields, poses)
        return labels

    def _fill_unseen(self, labels: Tensor, futures: list[Triplane], poses: Tensor) -> None:
        """Where a frame of ``labels`` looks beyond the present grid, what the forecast shows there:
        decoding those voxels alone. Where the host may read (:func:`~t3fast.host_syncs.reads_host`)
        it lists them; elsewhere the columns holding one are gathered to the front of a
        frame-sized buffer whose filled length stays on the device, and the decoder decodes every
        level of those columns only, every frame of every window in one call (a voxel decodes the
        same whatever else is decoded: the labels are the listed voxels')."""
        if not reads_host(labels.device):
            b, steps, nz = labels.shape[0], len(futures), labels.shape[-1]
            frames = labels[:, :steps].reshape(b * steps, -1, nz)  # [B * S, X * Y, Z]
            unseen = frames == IGNORE
            slot, columns, count = front_slots(unseen.any(2))  # the columns with an unseen voxel first
            points = column_queries(poses[:, :steps].flatten(0, 1).float(), self.decoder.grid, columns)
            planes = Triplane.stack(futures).map(lambda p: p.flatten(0, 1))  # frame k of window n at n * S + k
            decoded = self.decoder.predict(planes, points, live=count * nz).view_as(frames)
            fill = beyond_present(decoded).gather(1, slot.clamp(max=frames.shape[1] - 1)[..., None].expand_as(frames))
            labels[:, :steps] = torch.where(unseen, fill, frames).view(b, steps, *labels.shape[2:])
            return
        for k, future in enumerate(futures):
            for n in range(labels.shape[0]):
                frame = labels[n, k].view(-1)
                unseen = (frame == IGNORE).nonzero().squeeze(1)
                if unseen.numel():
                    points = voxel_queries(poses[n : n + 1, k].float(), self.decoder.grid, unseen)
                    decoded = self.decoder.predict(future.map(lambda p, n=n: p[n : n + 1]), points)
                    frame[unseen] = beyond_present(decoded.view(-1))

    #: what the render reads of a window's fitted boxes (:class:`~t3fast.agents.boxes.AgentBoxes`)
    BOX_FIELDS = ("length", "width", "bottom", "top", "label")

    @staticmethod
    def _draw_boxes(frames: Tensor, box_poses: Tensor, as_box: Tensor, length: Tensor, width: Tensor, bottom: Tensor,
                    top: Tensor, label: Tensor, poses: Tensor) -> None:
        """Drawn boxes into frames ``[..., S, X, Y, Z]`` at their poses ``[..., S, 3]``, all steps in
        one call: one window's (``as_box`` and the boxes' sizes, levels and labels ``[n]``,
        ``box_poses`` ``[S, n, 3]``) or several windows' (a leading dim on each). A box not drawn
        spans no level (its top is its bottom): the boxes keep their order, and no mask selects them
        (which would read it on the host)."""
        top = torch.where(as_box, top, bottom)
        # several windows' box attributes [N, n]: the same at each of a window's steps
        steps = (lambda t: t) if as_box.dim() == 1 else (lambda t: t[..., None, :])
        draw_agent_boxes(frames, box_poses[..., :2], box_poses[..., 2], steps(length), steps(width), steps(bottom),
                         steps(top), steps(label), poses)
