"""The agents' box fit of one window (:mod:`t3fast.agents.boxes`, 100 Adam steps, all agents at
once): Adam on the closed-form gradient (what the forecast runs) against ``torch.optim.Adam``
on autograd's gradient of the same objective (the fit as it was), on the same samples. Run with
``pytest benchmarks/test_bench_box_fit.py --benchmark-only``."""

from __future__ import annotations

import pytest
import torch

from t3fast.agents import boxes
from t3fast.agents.tracker import follow_agents, frame_agents
from t3fast.data.classes import AGENT_CLASSES
from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.models.ego_motion import planar_poses


def _window_problem() -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """A validation window's agents: their starting boxes ``[n, 7]`` and fit samples, as
    :func:`~t3fast.agents.boxes.fit_agent_boxes` builds them (every agent, none left out)."""
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    poses = planar_poses(sample.ego_poses[None], PRESENT)[0, : PRESENT + 1].double()
    agents = [frame_agents(f, torch.tensor(AGENT_CLASSES, dtype=f.dtype)) for f in sample.occ[: PRESENT + 1]]
    match = follow_agents(agents, poses)
    n = match.shape[0]
    start = torch.cat([boxes.cell_metres(agents[-1]["centroid"], poses[-1]), torch.zeros(n, 3, dtype=torch.float64),
                       torch.full((n, 2), 0.5, dtype=torch.float64).log()], 1)
    return start, boxes._samples(agents, match, poses, torch.full((n,), 8.0, dtype=torch.float64))


def _autograd_fit(start: torch.Tensor, found: dict[str, torch.Tensor], iters: int) -> torch.Tensor:
    agent = found["agent"]
    samples = boxes.FitSamples((found["position"] - start[agent, :2]).float(), found["time"].float(), agent,
                               found["owned"].float(), max(agent.numel(), 1))
    params = torch.cat([torch.zeros(start.shape[0], 2), start[:, 2:].float(), torch.zeros(start.shape[0], 2)], 1)
    params.requires_grad_(True)
    optimiser = torch.optim.Adam([params], lr=boxes.FIT_LR)
    with torch.enable_grad():
        for it in range(iters):
            softness = boxes.SOFTNESS[0] * (boxes.SOFTNESS[1] / boxes.SOFTNESS[0]) ** (it / max(iters - 1, 1))
            optimiser.zero_grad()
            boxes.fit_loss(params, samples, softness).backward()
            optimiser.step()
    return params.detach()


@pytest.mark.parametrize("impl", ["fused", "reference"])  # closed-form gradient / autograd
def test_box_fit(benchmark, impl):
    benchmark.group = "box fit of one window (100 Adam steps, one thread)"
    start, found = _window_problem()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the fit runs
    try:
        if impl == "fused":
            benchmark.pedantic(lambda: boxes._optimise(start, found, boxes.FIT_ITERS), rounds=5, warmup_rounds=1)
        else:
            benchmark.pedantic(lambda: _autograd_fit(start, found, boxes.FIT_ITERS), rounds=5, warmup_rounds=1)
    finally:
        torch.set_num_threads(threads)
    benchmark.extra_info["agents"] = start.shape[0]
    benchmark.extra_info["samples"] = found["agent"].numel()
