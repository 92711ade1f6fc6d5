"""box_fit: the fit's objective and closed-form gradient, its Adam steps, and the fused op
against the reference (start exact, a few steps within float32 round-off, a full fit within
the spread of an Adam fit started from the same box), on random and real windows; windows
fitted alone or together, agents not fitted or not found, odd sizes, empty, opcheck, compile,
thread counts."""

from __future__ import annotations

import math
from unittest import mock

import pytest
import torch

from t3fast import ops
from t3fast.agents import boxes as boxes_module
from t3fast.data.sample import PRESENT, collate_samples
from t3fast.data.synthetic import SyntheticDriving
from t3fast.evaluation.world_model import planar_poses
from t3fast.ops import reference
from t3fast.ops.reference import FitSamples, fit_gradient, fit_loss

LOWER, VOXEL = (-8.0, -9.6), 0.4
LR, SOFTNESS, PRIOR = 0.02, (0.1, 0.015), 3.0


def make(batch=2, agents=5, frames=4, shape=(40, 48), seed=0, device="cpu"):
    """Random windows: each agent a rectangle of columns in the frames where it is found, the
    frames' poses a little apart; a few agents not fitted (reach 0, NaN) or reaching past the
    window."""
    g = torch.Generator().manual_seed(seed)
    nx, ny = shape
    ids = torch.zeros(batch, frames, nx, ny, dtype=torch.long)
    for b in range(batch):
        for t in range(frames):
            for a in range(agents):
                if torch.rand(1, generator=g) < 0.85:
                    r, c = (torch.randint(0, n - 3, (1,), generator=g).item() for n in shape)
                    h, w = (torch.randint(1, 6, (1,), generator=g).item() for _ in range(2))
                    ids[b, t, r : r + h, c : c + w] = a + 1
    cells = torch.stack(torch.meshgrid(torch.arange(nx), torch.arange(ny), indexing="ij"), -1).double()
    owned = ids[:, :, None] == torch.arange(1, agents + 1).view(1, 1, -1, 1, 1)  # [B, T, n, X, Y]
    size = owned.sum((-2, -1)).double()
    centroid = (owned[..., None] * cells).sum((-3, -2)) / size[..., None]  # NaN where not found
    track = torch.where(size > 0, torch.arange(agents).view(1, 1, -1), -1).transpose(1, 2).contiguous()
    centroid = centroid.transpose(1, 2).contiguous()
    poses = torch.cat([torch.randn(batch, frames, 2, generator=g, dtype=torch.float64),
                       torch.randn(batch, frames, 1, generator=g, dtype=torch.float64) * 0.1], -1)
    poses[:, -1] = 0
    centre = torch.tensor(LOWER, dtype=torch.float64) + (centroid[:, :, -1].nan_to_num(10.0) + 0.5) * VOXEL
    start = torch.cat([centre, torch.randn(batch, agents, 2, generator=g, dtype=torch.float64) * 0.2,
                       torch.rand(batch, agents, 1, generator=g, dtype=torch.float64) * 3,
                       torch.rand(batch, agents, 2, generator=g, dtype=torch.float64).add(0.4).log()], -1)
    reach = torch.rand(batch, agents, generator=g, dtype=torch.float64) * 6 + 2
    reach[0, 0], reach[-1, -1] = 0.0, math.nan  # not fitted
    reach[0, 1] = 40.0  # capped at the window
    return [t.to(device) for t in (ids, track, centroid, poses, start, reach)]


def fit(args, iters, window=8, near=1, fn=ops.box_fit):
    return fn(*args, LOWER, VOXEL, window, near, iters, LR, SOFTNESS, PRIOR)


# ---------------------------------------------------------------- the objective and its steps
def _fit_problem(n: int = 3, per_agent: int = 40, seed: int = 0) -> tuple[torch.Tensor, FitSamples]:
    """Random boxes (float64) and samples around them, some inside, some on an edge."""
    g = torch.Generator().manual_seed(seed)
    params = torch.cat([torch.randn(n, 4, generator=g, dtype=torch.float64) * 0.3,
                        torch.rand(n, 1, generator=g, dtype=torch.float64) * 3,
                        torch.rand(n, 2, generator=g, dtype=torch.float64).add(0.3).log(),
                        torch.randn(n, 2, generator=g, dtype=torch.float64) * 0.1], 1)
    agent = torch.arange(n).repeat_interleave(per_agent)
    points = torch.randn(n * per_agent, 2, generator=g, dtype=torch.float64) * 1.5
    time = -torch.randint(0, 5, (n * per_agent,), generator=g).double()
    owned = (torch.rand(n * per_agent, generator=g) < 0.4).double()
    return params, FitSamples(points, time, agent, owned, n * per_agent)


@pytest.mark.parametrize("softness", [0.1, 0.015])
def test_the_closed_form_gradient_is_the_objectives_gradient(softness):
    params, samples = _fit_problem()
    params.requires_grad_(True)
    expected, = torch.autograd.grad(fit_loss(params, samples, softness, PRIOR), params)
    torch.testing.assert_close(fit_gradient(params.detach(), samples, softness, PRIOR), expected, rtol=1e-10,
                               atol=1e-12)


def test_the_gradient_splits_a_tie_between_length_and_width_as_torch_minimum_does():
    params = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, math.log(2.0), math.log(2.0), 0.0, 0.0]], dtype=torch.float64)
    points = torch.tensor([[0.5, 0.5], [0.2, -0.9]], dtype=torch.float64)  # on the diagonal: the margins tie
    samples = FitSamples(points, torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.long),
                         torch.tensor([1.0, 0.0], dtype=torch.float64), 2)
    params.requires_grad_(True)
    expected, = torch.autograd.grad(fit_loss(params, samples, 0.1, PRIOR), params)
    torch.testing.assert_close(fit_gradient(params.detach(), samples, 0.1, PRIOR), expected, rtol=1e-12, atol=1e-14)


def test_the_fit_descends_as_adam_on_its_objective_does():
    """The reference's own Adam steps (no autograd) against torch.optim.Adam on :func:`fit_loss`."""
    start, samples = _fit_problem(n=2, seed=3)
    fitted = start[:, :7].clone()
    found = {"position": samples.points, "time": samples.time, "agent": samples.agent, "owned": samples.owned}
    got, _ = reference.fit_adam(fitted.clone(), found, 30, LR, SOFTNESS, PRIOR)
    params = torch.cat([torch.zeros(2, 2), fitted[:, 2:].float(), torch.zeros(2, 2)], 1).requires_grad_(True)
    local = FitSamples((samples.points - fitted[samples.agent, :2]).float(), samples.time.float(), samples.agent,
                       samples.owned.float(), samples.count)
    optimiser = torch.optim.Adam([params], lr=LR)
    for it in range(30):
        optimiser.zero_grad()
        fit_loss(params, local, SOFTNESS[0] * (SOFTNESS[1] / SOFTNESS[0]) ** (it / 29), PRIOR).backward()
        optimiser.step()
    expected = params[:, :7].detach().double() + torch.cat([fitted[:, :2], torch.zeros(2, 5, dtype=torch.float64)], 1)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-4)


# ---------------------------------------------------------------- the op against the reference
@pytest.mark.parametrize("batch, agents, frames, shape, near", [
    (2, 5, 4, (40, 48), 1),
    (1, 9, 6, (23, 31), 0),  # odd sizes, no neighbourhood
    (3, 2, 1, (17, 9), 2),   # one frame
])
def test_without_steps_the_boxes_are_the_start_and_the_iou_the_references(device, batch, agents, frames, shape, near):
    args = make(batch, agents, frames, shape, device=device)
    got = fit(args, 0, near=near)
    want = fit(args, 0, near=near, fn=reference.box_fit)
    torch.testing.assert_close(got[0], want[0], rtol=0, atol=0)
    torch.testing.assert_close(got[1], want[1], rtol=0, atol=1e-6)
    assert (got[1] > 0).any()


@pytest.mark.parametrize("iters", [1, 3])
def test_a_few_steps_match_the_reference(device, iters):
    """Adam's first steps move every parameter by about the learning rate: a few steps are
    where a wrong gradient or step shows."""
    args = make(seed=1, device=device)
    got, want = fit(args, iters), fit(args, iters, fn=reference.box_fit)
    torch.testing.assert_close(got[0], want[0], rtol=0, atol=2e-3)
    assert (got[0] - args[4]).abs().max() > 0.01  # the steps moved the boxes
    torch.testing.assert_close(got[1], want[1], rtol=0, atol=0.05)


def test_agents_not_fitted_keep_their_start_and_an_iou_of_zero(device):
    args = make(device=device)
    boxes, iou = fit(args, 20)
    for b, a in ((0, 0), (-1, -1)):
        assert torch.equal(boxes[b, a], args[4][b, a]) and iou[b, a] == 0


def test_windows_are_fitted_on_their_own(device):
    """Each window's agents are fitted together (one normaliser), apart from the other windows."""
    args = make(batch=3, seed=2, device=device)
    together = fit(args, 10)
    alone = fit([t[1:2] for t in args], 10)
    torch.testing.assert_close(together[0][1:2], alone[0], rtol=0, atol=0)
    torch.testing.assert_close(together[1][1:2], alone[1], rtol=0, atol=0)


def _real_windows(count: int = 3) -> list[tuple]:
    """The op's arguments for the present agents of synthetic validation windows, as
    fit_agent_boxes passes them."""
    windows = SyntheticDriving("val", 2, 20, stride=9)
    with mock.patch.object(boxes_module.ops, "box_fit", wraps=ops.box_fit) as spy:
        for index in range(count):
            batch = collate_samples([windows[index]])
            poses = planar_poses(batch.ego_poses, PRESENT).double()[0][: PRESENT + 1]
            boxes_module.fit_agent_boxes(batch.past_occ[0], poses)
    return [call.args for call in spy.call_args_list]


def test_a_full_fit_on_real_windows_matches_the_reference():
    """100 Adam steps in float32 amplify round-off (each step is about the learning rate
    whatever the gradient's size, so a near-zero gradient's sign can differ): the boxes agree
    to a centimetre or so, the IoU but for a few small agents."""
    for args in _real_windows():
        (boxes, iou), (want, want_iou) = ops.box_fit(*args), reference.box_fit(*args)
        assert (boxes - want).abs().max() < 0.02
        assert (iou - want_iou).abs().max() < 0.15 and (iou - want_iou).abs().mean() < 0.01
        assert (want_iou > 0.5).sum() > 5  # real agents, fitted


def test_the_result_does_not_depend_on_the_thread_count():
    args = make(batch=3, agents=7, seed=5)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = fit(args, 15)
        torch.set_num_threads(max(threads, 2))
        many = fit(args, 15)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one[0], many[0]) and torch.equal(one[1], many[1])


def test_non_contiguous_inputs(device):
    args = make(seed=6, device=device)
    strided = [t.transpose(0, -1).contiguous().transpose(0, -1) if t.dim() > 1 else t for t in args]
    assert not strided[0].is_contiguous()
    got, want = fit(strided, 5), fit(args, 5)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


@pytest.mark.parametrize("batch, agents, frames", [(0, 3, 4), (2, 0, 4), (2, 3, 0)])
def test_empty(device, batch, agents, frames):
    ids = torch.zeros(batch, frames, 10, 10, dtype=torch.long, device=device)
    track = torch.full((batch, agents, frames), -1, dtype=torch.long, device=device)
    centroid = torch.zeros(batch, agents, frames, 2, dtype=torch.float64, device=device)
    poses = torch.zeros(batch, frames, 3, dtype=torch.float64, device=device)
    start = torch.ones(batch, agents, 7, dtype=torch.float64, device=device)
    reach = torch.full((batch, agents), 3.0, dtype=torch.float64, device=device)
    boxes, iou = fit((ids, track, centroid, poses, start, reach), 5)
    assert boxes.shape == (batch, agents, 7) and iou.shape == (batch, agents)
    assert torch.equal(iou, torch.zeros_like(iou))  # nothing sampled: nothing overlaps


def test_opcheck(device):
    args = make(batch=2, agents=3, frames=3, shape=(16, 18), seed=7, device=device)
    torch.library.opcheck(torch.ops.t3fast.box_fit.default,
                          (*args, list(LOWER), VOXEL, 6, 1, 4, LR, list(SOFTNESS), PRIOR))


def test_compiles_without_graph_breaks():
    args = make(seed=8)
    compiled = torch.compile(lambda *a: fit(a, 5), fullgraph=True, backend="aot_eager")
    got, want = compiled(*args), fit(args, 5)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


@pytest.mark.parametrize("change, match", [
    (lambda a: a.__setitem__(0, a[0].int()), "ids must be int64"),
    (lambda a: a.__setitem__(0, a[0][0]), r"ids must have 4 dims \[B, T, X, Y\]"),
    (lambda a: a.__setitem__(1, a[1][:, :, :-1]), r"track.shape\[2\] \(frames, as ids.shape\[1\]\)"),
    (lambda a: a.__setitem__(2, a[2].float()), "centroid must be float64"),
    (lambda a: a.__setitem__(3, a[3][:, :, :2]), r"poses must be \[B, T, 3\]"),
    (lambda a: a.__setitem__(4, a[4][:1]), r"start must be \[B, n, 7\]"),
    (lambda a: a.__setitem__(5, a[5][..., None]), r"reach must have 2 dims \[B, n\]"),
    (lambda a: a.__setitem__(5, a[5].to("meta")), "reach must be on the same device as ids"),
])
def test_bad_arguments_name_the_problem(change, match):
    args = make()
    change(args)
    with pytest.raises(RuntimeError, match=f"t3fast.box_fit: {match}"):
        fit(args, 2)


@pytest.mark.parametrize("change, match", [
    ({"window": -1}, r"window must be in \[0, 1024\]"),
    ({"near": 17}, r"near must be in \[0, 16\]"),
    ({"iters": -1}, "iters must be at least 0"),
    ({"lr": 0.0}, "lr must be positive"),
    ({"softness": (0.1, -1.0)}, "softness must hold two positive widths"),
    ({"lower": (0.0,)}, "lower must hold the grid's lower x and y"),
])
def test_bad_settings_name_the_problem(change, match):
    settings = {"lower": LOWER, "voxel": VOXEL, "window": 8, "near": 1, "iters": 2, "lr": LR, "softness": SOFTNESS}
    settings.update(change)
    with pytest.raises(RuntimeError, match=f"t3fast.box_fit: {match}"):
        ops.box_fit(*make(), *settings.values(), PRIOR)
