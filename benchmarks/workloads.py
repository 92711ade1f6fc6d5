"""Inputs of the benchmarked workloads, shared by the timed and the memory benchmarks."""

from __future__ import annotations

import torch

import t3fast.ops as fused
from t3fast.ops import reference

GRID = (200, 200, 16)  # Occ3D-nuScenes voxels
PLANES = (100, 100, 16)  # triplane resolution of the paper
# channels C_f, hidden width, hidden layers
DECODERS = {"small": (16, 64, 2), "paper": (64, 256, 4)}
IMPLS = {"fused": fused, "reference": reference}


def make_decode_inputs(decoder: str, batch: int = 1, classes: int = 18, pe_freqs: int = 6,
                       requires_grad: bool = False, seed: int = 0):
    """Planes, weights and biases of a decoder config (see DECODERS)."""
    channels, hidden, layers = DECODERS[decoder]
    g = torch.Generator().manual_seed(seed)
    px, py, pz = PLANES
    planes = [torch.randn(batch, channels, *s, generator=g) for s in ((px, py), (px, pz), (py, pz))]
    widths = [channels + 6 * pe_freqs, *[hidden] * layers, classes]
    weights = [torch.randn(o, i, generator=g) / i**0.5 for i, o in zip(widths[:-1], widths[1:])]
    biases = [torch.zeros(o) for o in widths[1:]]
    for t in (*planes, *weights, *biases):
        t.requires_grad_(requires_grad)
    return planes, weights, biases, pe_freqs


def run_decode(impl: str, args, query: str):
    """query: "grid" (full grid logits), "argmax" (full grid labels) or "points:N"."""
    planes, weights, biases, pe_freqs = args
    op = IMPLS[impl].triplane_decode
    if query == "grid":
        return op(*planes, weights, biases, grid=GRID, pe_freqs=pe_freqs)
    if query == "argmax":
        return op(*planes, weights, biases, grid=GRID, pe_freqs=pe_freqs, argmax=True)
    n = int(query.split(":")[1])
    points = torch.rand(planes[0].shape[0], n, 3, generator=torch.Generator().manual_seed(1))
    return op(*planes, weights, biases, points=points * 2 - 1, pe_freqs=pe_freqs)
