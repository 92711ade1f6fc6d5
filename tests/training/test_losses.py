"""Lovasz-softmax against a per-class reference, the CE + Lovasz combination, class weights."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from t3fast.data.classes import IGNORE
from t3fast.host_syncs import SyncCounter
from t3fast.training.losses import class_frequency_weights, lovasz_softmax, occupancy_loss


def _reference_lovasz(probs: torch.Tensor, labels: torch.Tensor, classes: str = "present") -> torch.Tensor:
    """Straightforward Berman et al. formulation: one sort per class, Jaccard built point by point."""
    keep = labels != IGNORE
    probs, labels = probs[keep], labels[keep]
    losses = []
    for c in range(probs.shape[1]):
        fg = (labels == c).double()
        if classes == "present" and fg.sum() == 0:
            continue
        errors = (fg - probs[:, c]).abs()
        errors_sorted, order = torch.sort(errors, descending=True)
        fg_sorted = fg[order]
        gts = fg_sorted.sum()
        jaccard = []
        for i in range(len(fg_sorted)):
            inter = gts - fg_sorted[: i + 1].sum()
            union = gts + (1 - fg_sorted[: i + 1]).sum()
            jaccard.append(1 - inter / union)
        jac = torch.stack(jaccard)
        grad = torch.cat([jac[:1], jac[1:] - jac[:-1]])
        losses.append(torch.dot(errors_sorted, grad))
    return torch.stack(losses).mean()


def _random_problem(seed: int, points: int = 60, classes: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    logits = torch.randn(points, classes, generator=gen, dtype=torch.float64)
    labels = torch.randint(0, classes - 1, (points,), generator=gen)  # the last class never occurs
    labels[torch.rand(points, generator=gen) < 0.2] = IGNORE
    return logits, labels


@pytest.mark.parametrize("classes", ["present", "all"])
def test_lovasz_matches_per_class_reference_value_and_gradient(classes: str) -> None:
    logits, labels = _random_problem(0)
    a = logits.clone().requires_grad_()
    b = logits.clone().requires_grad_()
    ours = lovasz_softmax(a.softmax(-1), labels, classes=classes)
    ref = _reference_lovasz(b.softmax(-1), labels, classes=classes)
    torch.testing.assert_close(ours, ref)
    ours.backward()
    ref.backward()
    torch.testing.assert_close(a.grad, b.grad)
    assert a.grad.abs().sum() > 0


def test_lovasz_gradcheck() -> None:
    logits, labels = _random_problem(1, points=12, classes=3)
    logits.requires_grad_()
    assert torch.autograd.gradcheck(lambda x: lovasz_softmax(x.softmax(-1), labels), (logits,))


def test_lovasz_explicit_class_list() -> None:
    logits, labels = _random_problem(2)
    probs = logits.softmax(-1)
    full = lovasz_softmax(probs, labels, classes="all")
    parts = [lovasz_softmax(probs, labels, classes=[c]) for c in range(probs.shape[1])]
    torch.testing.assert_close(full, torch.stack(parts).mean())


def test_lovasz_zero_for_perfect_prediction() -> None:
    labels = torch.tensor([0, 2, 2, 1, IGNORE, 3])
    probs = F.one_hot(labels.clamp(max=3), 4).double()
    assert lovasz_softmax(probs, labels).item() == 0.0
    wrong = F.one_hot((labels.clamp(max=3) + 1) % 4, 4).double()
    assert lovasz_softmax(wrong, labels).item() == pytest.approx(1.0)  # every class fully wrong


def test_lovasz_ignores_ignore_points() -> None:
    logits, labels = _random_problem(3)
    probs = logits.softmax(-1)
    keep = labels != IGNORE
    torch.testing.assert_close(lovasz_softmax(probs, labels), lovasz_softmax(probs[keep], labels[keep]))
    # what the ignored points predict does not matter
    shuffled = probs.clone()
    shuffled[~keep] = shuffled[~keep].flip(-1)
    torch.testing.assert_close(lovasz_softmax(shuffled, labels), lovasz_softmax(probs, labels))


def test_lovasz_all_ignored_is_zero_and_differentiable() -> None:
    probs = torch.rand(4, 3, requires_grad=True)
    loss = lovasz_softmax(probs, torch.full((4,), IGNORE))
    assert loss.item() == 0.0
    loss.backward()
    assert torch.equal(probs.grad, torch.zeros(4, 3))


def test_occupancy_loss_is_ce_plus_weighted_lovasz() -> None:
    gen = torch.Generator().manual_seed(4)
    logits = torch.randn(2, 30, 18, generator=gen, requires_grad=True)
    labels = torch.randint(0, 18, (2, 30), generator=gen).to(torch.uint8)
    labels[0, :5] = IGNORE
    loss, parts = occupancy_loss(logits, labels, lovasz_weight=0.5)
    flat, lab = logits.reshape(-1, 18), labels.reshape(-1).long()
    ce = F.cross_entropy(flat, lab, ignore_index=IGNORE)
    lov = lovasz_softmax(flat.softmax(-1), lab)
    torch.testing.assert_close(parts["ce"], ce.detach())
    torch.testing.assert_close(parts["lovasz"], lov.detach())
    torch.testing.assert_close(loss, ce + 0.5 * lov)
    assert not parts["ce"].requires_grad
    loss.backward()
    assert logits.grad[0, :5].abs().sum() == 0  # ignored points get no gradient
    assert logits.grad[1].abs().sum() > 0


def test_occupancy_loss_class_weights_and_no_lovasz() -> None:
    gen = torch.Generator().manual_seed(5)
    logits = torch.randn(40, 4, generator=gen)
    labels = torch.randint(0, 4, (40,), generator=gen)
    weights = torch.tensor([1.0, 3.0, 0.5, 2.0])
    loss, parts = occupancy_loss(logits, labels, class_weights=weights, lovasz_weight=0.0)
    torch.testing.assert_close(loss, F.cross_entropy(logits, labels, weight=weights))
    assert parts["lovasz"].item() == 0.0
    unweighted, _ = occupancy_loss(logits, labels, lovasz_weight=0.0)
    assert not torch.isclose(loss, unweighted)


def test_occupancy_loss_all_ignored_and_shape_check() -> None:
    logits = torch.randn(3, 4, requires_grad=True)
    loss, parts = occupancy_loss(logits, torch.full((3,), IGNORE))
    assert loss.item() == 0.0 and parts["ce"].item() == 0.0
    loss.backward()  # still part of the graph
    with pytest.raises(ValueError, match="do not match"):
        occupancy_loss(torch.randn(3, 4), torch.zeros(4, dtype=torch.long))


def test_class_frequency_weights() -> None:
    counts = torch.tensor([1e9, 1e6, 1e3, 0.0])
    w = class_frequency_weights(counts)
    assert w.dtype == torch.float32 and torch.isfinite(w).all() and (w > 0).all()
    assert (w[1:] > w[:-1]).all()  # rarer classes weigh more
    assert w[0].item() == pytest.approx(1 / math.log(1e9))
    assert w[3].item() == pytest.approx(1 / math.log(2))  # unseen: clamped to 2 voxels


def test_the_losses_read_nothing_on_the_host() -> None:
    """Ignored points are masked, not selected, so a GPU step never waits in its loss; the
    weighted mean is cross_entropy's over the points kept."""
    logits, labels = _random_problem(6)
    weights = torch.tensor([1.0, 3.0, 0.5, 2.0, 1.5], dtype=torch.float64)
    with SyncCounter() as counter:
        loss, parts = occupancy_loss(logits, labels, class_weights=weights, lovasz_weight=0.0)
        lovasz = lovasz_softmax(logits.softmax(-1), labels)
    assert counter.total == 0, counter.by_caller
    torch.testing.assert_close(parts["ce"], F.cross_entropy(logits.float(), labels, weight=weights.float(),
                                                            ignore_index=IGNORE))
    assert lovasz > 0
