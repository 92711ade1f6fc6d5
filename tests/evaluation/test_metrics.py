"""OccupancyMetrics: hand-computed examples, ignore/mask handling, merging, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.distributed as dist

from t3fast.data.classes import CAR, DRIVEABLE_SURFACE, FREE, IGNORE, TRUCK
from t3fast.evaluation.metrics import OccupancyMetrics

ROAD = DRIVEABLE_SURFACE


def _tiny() -> tuple[torch.Tensor, torch.Tensor]:
    """A 2x2x1 grid.

    target = [[car, free], [road, ignore]], pred = [[car, car], [free, road]].
    The ignore voxel is never scored, so three voxels count:
      v0 car->car (TP car), v1 free->car (FP car), v2 road->free (FN road).
    """
    target = torch.tensor([[[[CAR], [FREE]], [[ROAD], [IGNORE]]]], dtype=torch.uint8)
    pred = torch.tensor([[[[CAR], [CAR]], [[FREE], [ROAD]]]], dtype=torch.uint8)
    return pred, target


def test_hand_computed_example() -> None:
    pred, target = _tiny()
    m = OccupancyMetrics()
    m.update(pred, target)

    expected = torch.zeros(18, 18, dtype=torch.int64)
    expected[CAR, CAR] = expected[FREE, CAR] = expected[ROAD, FREE] = 1
    assert torch.equal(m.confusion, expected)

    iou = m.per_class_iou()
    assert iou.shape == (17,)
    # car: TP 1, FP 1, FN 0 -> 1/2; road: TP 0, FN 1 -> 0 (its prediction on the ignore voxel is not scored)
    assert iou[CAR] == pytest.approx(0.5)
    assert iou[ROAD] == 0.0
    # every other class is in neither prediction nor target
    others = [c for c in range(17) if c not in (CAR, ROAD)]
    assert torch.isnan(iou[others]).all()
    # OccWorld: the 15 classes without ground truth count 1 -> (0.5 + 0 + 15) / 17
    assert m.miou() == pytest.approx(15.5 / 17)
    assert m.miou(absent="skip") == pytest.approx(0.25)
    # occupied vs free: TP v0, FP v1, FN v2 -> 1/3
    assert m.iou() == pytest.approx(1 / 3)


def test_mask_restricts_scoring() -> None:
    pred, target = _tiny()
    mask = torch.tensor([[[[True], [False]], [[True], [True]]]])
    m = OccupancyMetrics()
    m.update(pred, target, mask=mask)
    # v1 masked out: car TP 1 -> 1; road FN 1 -> 0; binary TP 1, FN 1 -> 1/2
    assert m.per_class_iou()[CAR] == 1.0
    assert m.per_class_iou()[ROAD] == 0.0
    assert m.iou() == pytest.approx(0.5)
    assert int(m.confusion.sum()) == 2


def test_predicted_class_without_ground_truth_counts_one_in_miou() -> None:
    # target all free, a truck predicted in one voxel: plain IoU of truck is 0 ...
    target = torch.full((1, 2, 1, 1), FREE, dtype=torch.uint8)
    pred = torch.tensor([TRUCK, FREE], dtype=torch.uint8).view(1, 2, 1, 1)
    m = OccupancyMetrics()
    m.update(pred, target)
    assert m.per_class_iou()[TRUCK] == 0.0
    # ... but OccWorld scores a class by its ground truth only, so every class counts 1
    assert m.miou() == 1.0
    assert math.isnan(m.miou(absent="skip"))
    assert m.absent_classes() == list(range(17))
    assert m.iou() == 0.0  # one FP, no TP


def _reference_confusion(pred: np.ndarray, target: np.ndarray, mask: np.ndarray) -> np.ndarray:
    conf = np.zeros((18, 18), dtype=np.int64)
    keep = (target != IGNORE) & mask
    np.add.at(conf, (target[keep].astype(np.int64), pred[keep].astype(np.int64)), 1)
    return conf


def _random_batch(gen: torch.Generator, shape=(2, 8, 8, 4)) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    target = torch.randint(0, 18, shape, generator=gen, dtype=torch.uint8)
    target[torch.rand(shape, generator=gen) < 0.1] = IGNORE
    pred = torch.randint(0, 18, shape, generator=gen, dtype=torch.uint8)
    mask = torch.rand(shape, generator=gen) < 0.8
    return pred, target, mask


def test_matches_reference_and_iou_formula() -> None:
    gen = torch.Generator().manual_seed(0)
    pred, target, mask = _random_batch(gen)
    m = OccupancyMetrics()
    m.update(pred.long(), target.long(), mask=mask)
    conf = _reference_confusion(pred.numpy(), target.numpy(), mask.numpy())
    assert np.array_equal(m.confusion.numpy(), conf)
    tp = np.diag(conf)[:17]
    union = conf.sum(0)[:17] + conf.sum(1)[:17] - tp
    np.testing.assert_allclose(m.per_class_iou().numpy(), tp / union)
    assert m.miou() == pytest.approx(float(np.mean(tp / union)))
    occ_t = conf[:17].sum(1)  # rows: target occupied
    tp_occ = conf[:17, :17].sum()
    fp_occ = conf[17, :17].sum()
    assert m.iou() == pytest.approx(tp_occ / (occ_t.sum() + fp_occ))


def test_merge_equals_single_accumulation() -> None:
    gen = torch.Generator().manual_seed(1)
    batches = [_random_batch(gen) for _ in range(3)]
    single, first, second = OccupancyMetrics(), OccupancyMetrics(), OccupancyMetrics()
    for i, (p, t, k) in enumerate(batches):
        single.update(p, t, mask=k)
        (first if i < 2 else second).update(p, t, mask=k)
    assert first.merge(second) is first
    assert torch.equal(first.confusion, single.confusion)
    assert first.miou() == single.miou() and first.iou() == single.iou()
    single.reset()
    assert int(single.confusion.sum()) == 0


def test_all_reduce_without_and_with_process_group(tmp_path) -> None:
    pred, target = _tiny()
    m = OccupancyMetrics()
    m.update(pred, target)
    before = m.confusion.clone()
    assert m.all_reduce() is m  # not initialised: a no-op
    assert torch.equal(m.confusion, before)
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'pg'}", rank=0, world_size=1)
    try:
        m.all_reduce()
    finally:
        dist.destroy_process_group()
    assert torch.equal(m.confusion, before)  # world size 1: sum over one process


def test_summary_and_table() -> None:
    pred, target = _tiny()
    m = OccupancyMetrics()
    m.update(pred, target)
    s = m.summary()
    assert s["miou"] == pytest.approx(100 * 15.5 / 17)
    assert s["iou"] == pytest.approx(100 / 3)
    assert list(s["per_class"])[CAR] == "car"
    assert s["per_class"]["car"] == pytest.approx(50.0)
    assert "free" not in s["per_class"]
    assert "car" not in s["absent"] and "driveable_surface" not in s["absent"] and "bus" in s["absent"]
    table = m.table()
    assert "| car | 50.00 |" in table
    assert "| bus | nan (no ground truth: 100 in mIoU) |" in table
    assert f"| **mIoU** | {100 * 15.5 / 17:.2f} |" in table
    assert len(table.splitlines()) == 2 + 17 + 2


@pytest.mark.parametrize(
    ("pred", "target", "mask", "message"),
    [
        (torch.zeros(2, 3, dtype=torch.long), torch.zeros(3, 2, dtype=torch.long), None, "shape"),
        (torch.zeros(4, dtype=torch.long), torch.zeros(4, dtype=torch.long), torch.ones(3, dtype=torch.bool), "mask"),
        (torch.full((4,), 18), torch.zeros(4, dtype=torch.long), None, "pred labels"),
        (torch.full((4,), -1), torch.zeros(4, dtype=torch.long), None, "pred labels"),
        (torch.zeros(4, dtype=torch.long), torch.full((4,), 200), None, "target label 200"),
        (torch.zeros(4, dtype=torch.long), torch.full((4,), -3), None, "target label -3"),
        (torch.zeros(4), torch.zeros(4, dtype=torch.long), None, "integer dtype"),
    ],
)
def test_bad_input(pred, target, mask, message) -> None:
    m = OccupancyMetrics()
    with pytest.raises(ValueError, match=message):
        m.update(pred, target, mask=mask)
    assert int(m.confusion.sum()) == 0


def test_bad_construction_and_merge() -> None:
    with pytest.raises(ValueError, match="ignore_index"):
        OccupancyMetrics(ignore_index=3)
    with pytest.raises(ValueError, match="incompatible"):
        OccupancyMetrics().merge(OccupancyMetrics(num_classes=5, free_class=4, class_names=tuple("abcde")))
    with pytest.raises(ValueError, match="absent"):
        OccupancyMetrics().miou(absent="zero")


def test_moving_class_miou_averages_the_agent_classes() -> None:
    from t3fast.data.classes import BUS, MOVING_CLASSES

    assert sorted(MOVING_CLASSES) == [2, 3, 4, 5, 6, 7, 9, 10]
    # every semantic class but bus has 4 voxels, all right except car: 1 of its 4 predicted car, 3 free
    target = torch.tensor([c for c in range(17) if c != BUS for _ in range(4)], dtype=torch.uint8)
    pred = target.clone()
    pred[(target == CAR).nonzero()[1:, 0]] = FREE
    m = OccupancyMetrics()
    m.update(pred, target)
    assert m.per_class_iou()[CAR] == pytest.approx(0.25)
    # bus has no ground truth: 1 under OccWorld's rule, left out with "skip"
    assert m.miou(classes=MOVING_CLASSES) == pytest.approx((7 + 0.25) / 8)
    assert m.miou("skip", MOVING_CLASSES) == pytest.approx((6 + 0.25) / 7)
    assert m.miou() == pytest.approx((16 + 0.25) / 17)
    with pytest.raises(ValueError, match="subset"):
        m.miou(classes=[FREE])


def test_report_tables_show_the_moving_class_miou() -> None:
    from t3fast.evaluation.report import metrics_markdown

    occ = {"0s": None, "1s": 50.0, "2s": 40.0, "3s": 30.0, "avg": 40.0}
    plan = dict.fromkeys(("1s", "2s", "3s", "avg"))
    record = dict(miou=occ, iou=occ, miou_moving={"0s": None, "1s": 12.5, "2s": 10.0, "3s": 7.5, "avg": 10.0},
                  l2_at=plan, l2_mean=plan, collision=plan, fps=None, peak_memory_mb=None, params=None)
    old = {k: v for k, v in record.items() if k != "miou_moving"}  # a record written before the column
    text = metrics_markdown({"track_const_vel": record, "old": old})
    assert "| moving mIoU 1s / 2s / 3s | moving mIoU avg |" in text
    assert "| 12.50 / 10.00 / 7.50 | 10.00 |" in text and "| - / - / - | - |" in text
