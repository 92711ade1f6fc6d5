"""Distributed helpers: no-ops in one process; two gloo processes train to identical weights."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import torch
import torch.multiprocessing as mp

from t3fast.io.checkpoint import load_checkpoint
from t3fast.training import distributed as dist_utils
from t3fast.training.trainer import Trainer

from .test_trainer import ToyTask, toy_config

STEPS = 4


def test_helpers_are_no_ops_in_one_process() -> None:
    assert not dist_utils.is_distributed()
    assert dist_utils.world_size() == 1 and dist_utils.rank() == 0 and dist_utils.is_main()
    assert dist_utils.init_distributed("cpu") == torch.device("cpu")
    assert not dist_utils.is_distributed()
    t = torch.tensor([1.0, 2.0])
    assert dist_utils.all_reduce_mean(2.5) == 2.5 and dist_utils.all_reduce_mean(t) is t
    assert dist_utils.all_reduce_mean({"a": 1.0}) == {"a": 1.0}
    assert dist_utils.any_rank(True) and not dist_utils.any_rank(False)
    assert dist_utils.all_gather_object({"x": 1}) == [{"x": 1}]
    dist_utils.barrier()
    dist_utils.cleanup()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(rank: int, world: int, port: int, out_dir: str) -> None:
    os.environ.update(
        RANK=str(rank), LOCAL_RANK=str(rank), WORLD_SIZE=str(world), MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port)
    )
    torch.set_num_threads(1)
    try:
        trainer = Trainer(ToyTask(stochastic=False), toy_config(Path(out_dir), steps=STEPS, batch_size=2))
        assert dist_utils.world_size() == world and dist_utils.rank() == rank
        torch.save(trainer.module.state_dict(), Path(out_dir) / f"start{rank}.pt")
        trainer.fit()
        # every rank evaluated the same weights, so the mean equals each rank's value
        score = trainer.task.evaluate(trainer.module)["score"]
        assert dist_utils.all_reduce_mean(score) == score
        torch.save(trainer.module.state_dict(), Path(out_dir) / f"end{rank}.pt")
    finally:
        dist_utils.cleanup()


def test_two_gloo_processes_train_identically(tmp_path: Path) -> None:
    ddp_dir = tmp_path / "ddp"
    mp.spawn(_worker, args=(2, _free_port(), str(ddp_dir)), nprocs=2, join=True)

    start = torch.load(ddp_dir / "start0.pt")
    end0, end1 = torch.load(ddp_dir / "end0.pt"), torch.load(ddp_dir / "end1.pt")
    for k in end0:
        assert torch.equal(end0[k], end1[k]), k
        assert not torch.equal(end0[k], start[k]), k
    assert load_checkpoint(ddp_dir / "last.pt")["step"] == STEPS

    # 2 ranks x 2 samples see the same global batches as 1 process x 4 samples
    single = Trainer(ToyTask(stochastic=False), toy_config(tmp_path / "single", steps=STEPS, batch_size=4))
    single.fit()
    for k, v in single.module.state_dict().items():
        torch.testing.assert_close(end0[k], v, rtol=1e-5, atol=1e-6)
