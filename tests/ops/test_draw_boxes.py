"""draw_boxes: parity with the reference (all boxes at once, the last one winning), the
footprint and centre-column rules, order, clipping at the grid's edges, opcheck, compile."""

from __future__ import annotations

import math

import pytest
import torch

from t3fast.ops import draw_boxes, reference

LOWER, VOXEL = (-40.0, -40.0), 0.4


def make(batch, count, shape=(200, 200, 16), seed=0, device="cpu"):
    """Random volumes and boxes anywhere on and around the grid, some overlapping."""
    g = torch.Generator().manual_seed(seed)
    volume = torch.randint(0, 18, (batch, *shape), generator=g, dtype=torch.uint8)
    extent = torch.tensor(shape[:2], dtype=torch.float64) * VOXEL
    centre = torch.rand(batch, count, 2, generator=g, dtype=torch.float64) * (extent + 8) + torch.tensor(LOWER) - 4
    heading = torch.rand(batch, count, generator=g, dtype=torch.float64) * 2 * math.pi - math.pi
    half = torch.rand(batch, count, 2, generator=g, dtype=torch.float64) * torch.tensor([4.0, 1.5]) + 0.1
    boxes = torch.cat([centre, heading.cos()[..., None], heading.sin()[..., None], half], -1)
    bottom = torch.randint(-2, shape[2], (count,), generator=g)
    levels = torch.stack([bottom, bottom + torch.randint(0, 9, (count,), generator=g)], -1)
    labels = torch.randint(0, 18, (count,), generator=g, dtype=torch.uint8)
    return [t.to(device) for t in (volume, boxes, levels, labels)]


@pytest.mark.parametrize("batch, count, shape, reach", [
    (1, 0, (200, 200, 16), 26),   # no box: the volume unchanged
    (2, 1, (200, 200, 16), 26),
    (3, 40, (200, 200, 16), 26),  # a forecast's agents, overlapping
    (2, 25, (17, 9, 5), 3),       # odd sizes, boxes larger than their window
    (1, 7, (1, 1, 1), 0),         # one voxel: only the centre column
    (0, 4, (10, 10, 4), 2),       # empty batch
])
def test_matches_reference(device, batch, count, shape, reach):
    volume, boxes, levels, labels = make(batch, count, shape, device=device)
    got = draw_boxes(volume, boxes, levels, labels, LOWER, VOXEL, reach)
    want = reference.draw_boxes(volume, boxes, levels, labels, LOWER, VOXEL, reach)
    assert got.dtype == torch.uint8 and got.shape == volume.shape and torch.equal(got, want)


@pytest.mark.parametrize("batch, count, shape, reach", [(3, 40, (200, 200, 16), 26), (2, 25, (17, 9, 5), 3),
                                                        (0, 4, (10, 10, 4), 2)])
def test_each_volume_its_own_levels_and_labels(device, batch, count, shape, reach):
    """levels [B, M, 2] and labels [B, M]: several windows' boxes in one call, each volume as if
    drawn alone with its own, and as the reference draws them."""
    volume, boxes, _, _ = make(batch, count, shape, device=device)
    g = torch.Generator().manual_seed(1)
    bottom = torch.randint(-2, shape[2], (batch, count), generator=g)
    levels = torch.stack([bottom, bottom + torch.randint(0, 9, (batch, count), generator=g)], -1).to(device)
    labels = torch.randint(0, 18, (batch, count), generator=g, dtype=torch.uint8).to(device)
    got = draw_boxes(volume, boxes, levels, labels, LOWER, VOXEL, reach)
    assert torch.equal(got, reference.draw_boxes(volume, boxes, levels, labels, LOWER, VOXEL, reach))
    for n in range(batch):
        alone = draw_boxes(volume[n : n + 1], boxes[n : n + 1], levels[n], labels[n], LOWER, VOXEL, reach)
        assert torch.equal(got[n : n + 1], alone)
    if batch > 1:  # the volumes' levels differ: the same boxes with the first volume's draw otherwise
        shared = draw_boxes(volume, boxes, levels[0], labels[0], LOWER, VOXEL, reach)
        assert not torch.equal(got[1:], shared[1:])


def test_a_box_fills_the_columns_whose_centres_it_covers_over_its_levels():
    volume = torch.zeros(1, 10, 10, 4, dtype=torch.uint8)
    # a box 1.22 m long along x and 0.42 m wide at the centre of column (4, 5): rows 3 to 5 of column 5
    boxes = torch.tensor([[[-40 + 0.4 * 4.5, -40 + 0.4 * 5.5, 1.0, 0.0, 0.61, 0.21]]], dtype=torch.float64)
    out = draw_boxes(volume, boxes, torch.tensor([[1, 3]]), torch.tensor([7], dtype=torch.uint8), LOWER, VOXEL, 5)
    drawn = (out[0] == 7).nonzero().tolist()
    assert drawn == [[x, 5, z] for x in (3, 4, 5) for z in (1, 2)]


def test_a_small_box_keeps_its_centre_column_and_a_later_box_wins():
    volume = torch.zeros(1, 6, 6, 2, dtype=torch.uint8)
    tiny = [-40 + 0.4 * 2.3, -40 + 0.4 * 2.7, 1.0, 0.0, 0.01, 0.01]  # covers no column centre
    wide = [-40 + 0.4 * 2.5, -40 + 0.4 * 2.5, 1.0, 0.0, 0.5, 0.5]
    boxes = torch.tensor([[tiny, wide]], dtype=torch.float64)
    levels = torch.tensor([[0, 2], [1, 2]])
    out = draw_boxes(volume, boxes, levels, torch.tensor([3, 9], dtype=torch.uint8), LOWER, VOXEL, 2)[0]
    assert out[2, 2].tolist() == [3, 9]  # level 0 is the tiny box's alone, level 1 the later box's
    assert (out[..., 1] == 9).sum() == 9 and (out[..., 0] == 3).sum() == 1
    swapped = draw_boxes(volume, boxes.flip(1), levels.flip(0), torch.tensor([9, 3], dtype=torch.uint8), LOWER,
                         VOXEL, 2)[0]
    assert swapped[2, 2].tolist() == [3, 3]


def test_non_contiguous_inputs(device):
    volume, boxes, levels, labels = make(2, 12, (30, 40, 6), seed=3, device=device)
    strided = volume.transpose(1, 2).contiguous().transpose(1, 2)
    assert not strided.is_contiguous()
    got = draw_boxes(strided, boxes.transpose(0, 1).contiguous().transpose(0, 1), levels, labels, LOWER, VOXEL, 6)
    assert torch.equal(got, draw_boxes(volume, boxes, levels, labels, LOWER, VOXEL, 6))


def test_opcheck(device):
    volume, boxes, levels, labels = make(2, 5, (20, 20, 4), seed=4, device=device)
    torch.library.opcheck(torch.ops.t3fast.draw_boxes.default, (volume, boxes, levels, labels, list(LOWER), VOXEL, 4))


def test_torch_compile_fullgraph(device):
    volume, boxes, levels, labels = make(2, 8, (30, 30, 4), seed=5, device=device)
    compiled = torch.compile(lambda v, b: draw_boxes(v, b, levels, labels, LOWER, VOXEL, 5), fullgraph=True,
                             backend="aot_eager")
    assert torch.equal(compiled(volume, boxes), draw_boxes(volume, boxes, levels, labels, LOWER, VOXEL, 5))
