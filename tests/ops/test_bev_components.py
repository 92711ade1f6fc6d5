"""bev_components: parity with the label-propagation reference and with a flood fill, the
documented numbering, opcheck and torch.compile (the op reads nothing on the host)."""

from __future__ import annotations

import pytest
import torch

from t3fast.ops import bev_components, reference


def flood_fill(mask: torch.Tensor) -> tuple[torch.Tensor, int]:
    """One mask ``[X, Y]``'s 8-connected components numbered by their last cell (row-major)."""
    nx, ny = mask.shape
    seen = torch.zeros(nx, ny, dtype=torch.long)
    members = []
    for start in zip(*mask.nonzero(as_tuple=True)):
        start = (int(start[0]), int(start[1]))
        if seen[start]:
            continue
        seen[start], stack, cells = -1, [start], []
        while stack:
            x, y = stack.pop()
            cells.append((x, y))
            for dx in (-1, 0, 1):
                for dy in (-1, 0, 1):
                    a, b = x + dx, y + dy
                    if 0 <= a < nx and 0 <= b < ny and mask[a, b] and not seen[a, b]:
                        seen[a, b] = -1
                        stack.append((a, b))
        members.append(cells)
    members.sort(key=max)
    labels = torch.zeros(nx, ny, dtype=torch.long)
    for number, cells in enumerate(members, 1):
        for cell in cells:
            labels[cell] = number
    return labels, len(members)


def random_masks(shape, density, seed=0):
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) < density


def spiral(n: int) -> torch.Tensor:
    """A one-cell-wide spiral over an ``n x n`` grid: one component of diameter ~n^2 / 2."""
    mask = torch.zeros(n, n, dtype=torch.bool)
    lo, hi = 0, n - 1
    while lo <= hi:
        mask[lo, lo:hi + 1] = True
        mask[lo:hi + 1, hi] = True
        mask[hi, lo + 2:hi + 1] = True
        mask[lo + 2:hi + 1, lo + 2] = lo + 2 <= hi
        lo, hi = lo + 2, hi - 2
    return mask


@pytest.mark.parametrize("shape, density", [
    ((3, 200, 200), 0.02),   # Occ3D's BEV grid, agent-like density
    ((2, 17, 31), 0.5),      # odd sizes near the percolation threshold: long, branching components
    ((4, 9, 5), 0.8),
    ((1, 1, 1), 1.0),
    ((1, 1, 40), 0.6),
    ((1, 40, 1), 0.6),
])
def test_matches_the_reference_and_a_flood_fill(device, shape, density):
    mask = random_masks(shape, density).to(device)
    labels, count = bev_components(mask)
    want, want_count = reference.bev_components(mask)
    assert labels.dtype == count.dtype == torch.long and labels.device == mask.device
    assert torch.equal(labels, want) and torch.equal(count, want_count)
    for b in range(shape[0]):
        fill, n = flood_fill(mask[b].cpu())
        assert torch.equal(labels[b].cpu(), fill) and int(count[b]) == n


def test_numbers_components_by_their_last_cell():
    mask = torch.tensor([[1, 0, 0, 1],
                         [0, 1, 0, 0],
                         [0, 0, 0, 1]], dtype=torch.bool)
    labels, count = bev_components(mask[None])
    # the diagonal pair ends at (1, 1), the lone corner cells at (0, 3) and (2, 3)
    assert labels[0].tolist() == [[2, 0, 0, 1], [0, 2, 0, 0], [0, 0, 0, 3]]
    assert count.tolist() == [3]


def test_a_long_spiral_is_one_component(device):
    mask = spiral(63)[None].to(device)
    labels, count = bev_components(mask)
    assert count.tolist() == [1] and torch.equal(labels, mask.long())
    assert torch.equal(labels, reference.bev_components(mask)[0])


@pytest.mark.parametrize("shape", [(0, 5, 5), (2, 0, 4), (2, 4, 0)])
def test_empty(device, shape):
    labels, count = bev_components(torch.zeros(shape, dtype=torch.bool, device=device))
    assert labels.shape == shape and count.shape == (shape[0],) and not count.any()


def test_no_cell_and_every_cell(device):
    labels, count = bev_components(torch.zeros(2, 6, 7, dtype=torch.bool, device=device))
    assert not labels.any() and count.tolist() == [0, 0]
    labels, count = bev_components(torch.ones(2, 6, 7, dtype=torch.bool, device=device))
    assert (labels == 1).all() and count.tolist() == [1, 1]


def test_non_contiguous_mask(device):
    mask = random_masks((2, 30, 20), 0.4, seed=3).to(device)
    strided = mask.transpose(1, 2)
    assert not strided.is_contiguous()
    got = bev_components(strided)
    want = bev_components(strided.contiguous())
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


def test_opcheck(device):
    mask = random_masks((2, 11, 13), 0.4, seed=4).to(device)
    torch.library.opcheck(torch.ops.t3fast.bev_components.default, (mask,))


def test_torch_compile_fullgraph_reads_nothing_on_the_host(device):
    mask = random_masks((2, 50, 40), 0.1, seed=5).to(device)
    compiled = torch.compile(bev_components, fullgraph=True, backend="aot_eager")
    got, want = compiled(mask), bev_components(mask)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
