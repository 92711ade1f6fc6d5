"""Class-id helpers."""

from __future__ import annotations

import pytest
import torch

from t3fast.data.classes import AGENT_CLASSES, FLAT_GROUND_CLASSES, IGNORE, in_classes


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int32, torch.int64])
@pytest.mark.parametrize("classes", [AGENT_CLASSES, FLAT_GROUND_CLASSES, (IGNORE,), ()])
def test_in_classes_is_isin(dtype, classes):
    g = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 18, (3, 7, 5, 4), generator=g).to(dtype)
    labels[0, 0] = IGNORE
    wanted = torch.tensor(classes, dtype=torch.long)
    got = in_classes(labels, wanted)
    assert got.dtype == torch.bool and got.shape == labels.shape
    assert torch.equal(got, torch.isin(labels.long(), wanted))
    strided = labels.transpose(1, 3)  # a view that is not contiguous
    assert torch.equal(in_classes(strided, wanted), torch.isin(strided.long(), wanted))
