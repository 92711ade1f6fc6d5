"""Training sets gathered a batch at a time (:mod:`t3fast.training.gathered`): through the
trainer's loader a batch holds exactly its items' rows, collated once; held in host memory the
rows are not copied; a set held on an accelerator gets a loader without worker processes."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch.utils.data import DataLoader

from t3fast.training.batch_sampler import ResumableBatchSampler
from t3fast.training.gathered import GatheredBatches, fits_on, held_on_device
from t3fast.training.trainer import Trainer
from tests.training.test_trainer import ToyTask, toy_config


def rows(n: int = 10) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(n)
    return {"x": torch.randn(n, 3, generator=g), "item": torch.arange(n),
            "half": torch.randn(n, 2, 2, generator=g).half()}


def test_a_batch_is_its_items_rows_through_the_trainers_loader():
    fields = rows()
    data = GatheredBatches(fields)
    loader = DataLoader(data, batch_sampler=ResumableBatchSampler(len(data), 3, seed=0), collate_fn=lambda b: b)
    seen = []
    for batch in loader:
        index = batch["item"]
        assert index.shape == (3,)
        for name, t in fields.items():
            assert batch[name].dtype == t.dtype and torch.equal(batch[name], t[index]), name
        seen += index.tolist()
    assert len(seen) == len(set(seen)) == 9  # one epoch of whole batches, each item at most once


def test_held_in_host_memory_the_rows_are_not_copied():
    fields = rows()
    for asked in ("cpu", "meta"):  # only a CUDA device with room holds them
        data = GatheredBatches(fields, asked)
        assert data.device == torch.device("cpu") and not held_on_device(data)
        assert all(data.fields[k].data_ptr() == t.data_ptr() for k, t in fields.items())
    assert not fits_on(torch.device("cpu"), 1)


def test_every_item_at_once_and_an_empty_set():
    fields = rows()
    assert all(torch.equal(GatheredBatches(fields).all()[k], t) for k, t in fields.items())
    empty = GatheredBatches(rows(0))
    assert len(empty) == 0 and empty.all()["x"].shape == (0, 3)


def test_fields_of_different_lengths_are_refused():
    with pytest.raises(ValueError, match=r"one row per item.*'a': 3, 'b': 4"):
        GatheredBatches({"a": torch.zeros(3), "b": torch.zeros(4, 2)})


class HeldOn(GatheredBatches):
    """The toy task's data, as if held on ``device``."""

    def __init__(self, fields: dict[str, torch.Tensor], device: str):
        super().__init__(fields)
        self.device = torch.device(device)


@pytest.mark.parametrize("device, workers", [("cpu", 2), ("meta", 0)])
def test_a_set_held_on_an_accelerator_gets_a_loader_without_workers(tmp_path: Path, device: str, workers: int):
    task = ToyTask()
    task.train_dataset = lambda: HeldOn({"x": task.x, "y": task.y}, device)
    trainer = Trainer(task, toy_config(tmp_path, num_workers=2))
    assert trainer.loader.num_workers == workers and not trainer.loader.pin_memory
