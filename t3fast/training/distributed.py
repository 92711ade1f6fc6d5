"""Multi-process training helpers for ``torchrun``; every function is a no-op in a single process.

Launch with ``torchrun --nproc_per_node N script.py``: torchrun sets RANK, WORLD_SIZE,
LOCAL_RANK, MASTER_ADDR and MASTER_PORT, and :func:`init_distributed` joins the group
(NCCL on GPU, gloo on CPU). Call :func:`cleanup` when the script is done.
"""

from __future__ import annotations

import os
from typing import Any, TypeVar

import torch
import torch.distributed as dist

from t3fast.device import default_device

V = TypeVar("V", float, torch.Tensor, dict)


def init_distributed(device: str = "auto") -> torch.device:
    """Join the process group described by the torchrun environment and return this process's device.

    Args:
        device: ``"auto"`` (CUDA when available), ``"cuda"`` or ``"cpu"``. With CUDA each process
            uses ``cuda:LOCAL_RANK`` and NCCL; on CPU the backend is gloo.

    Without WORLD_SIZE > 1 in the environment no group is created. Calling it again is harmless.
    """
    kind = default_device().type if device == "auto" else device
    if kind not in ("cuda", "cpu"):
        raise ValueError(f"init_distributed: device must be 'auto', 'cuda' or 'cpu', got {device!r}")
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    dev = torch.device("cuda", local_rank) if kind == "cuda" else torch.device("cpu")
    if dev.type == "cuda":
        torch.cuda.set_device(dev)  # NCCL and the default cuda tensors then use this process's GPU
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not is_distributed():
        backend = "nccl" if dev.type == "cuda" else "gloo"
        # device_id binds NCCL to this GPU at once instead of guessing later
        dist.init_process_group(backend=backend, device_id=dev if dev.type == "cuda" else None)
    return dev


def is_distributed() -> bool:
    """Whether a process group is active."""
    return dist.is_available() and dist.is_initialized()


def world_size() -> int:
    """Number of processes (1 when not distributed)."""
    return dist.get_world_size() if is_distributed() else 1


def rank() -> int:
    """This process's global rank (0 when not distributed)."""
    return dist.get_rank() if is_distributed() else 0


def is_main() -> bool:
    """True on rank 0, the process that logs and writes files."""
    return rank() == 0


def barrier() -> None:
    """Wait until every process gets here."""
    if is_distributed():
        dist.barrier()


def all_reduce_mean(value: V) -> V:
    """Mean over processes of a float, a tensor, or a ``dict[str, float]`` (same keys on every rank)."""
    if not is_distributed():
        return value
    if isinstance(value, dict):
        keys = sorted(value)
        means = all_reduce_mean(torch.tensor([float(value[k]) for k in keys], dtype=torch.float64))
        return {k: float(m) for k, m in zip(keys, means.tolist())}
    if isinstance(value, torch.Tensor):
        out = value.detach().to(_comm_device(), copy=True)
        dist.all_reduce(out, op=dist.ReduceOp.SUM)
        return (out / world_size()).to(value.device)
    return float(all_reduce_mean(torch.tensor(float(value), dtype=torch.float64)))


def any_rank(flag: bool) -> bool:
    """True on every process if ``flag`` is true on any (e.g. to stop all ranks at the same step)."""
    if not is_distributed():
        return flag
    t = torch.tensor(int(flag), device=_comm_device())
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def all_gather_object(obj: Any) -> list[Any]:
    """Every process's ``obj`` (picklable), in rank order; ``[obj]`` when not distributed."""
    if not is_distributed():
        return [obj]
    out: list[Any] = [None] * world_size()
    dist.all_gather_object(out, obj)
    return out


def cleanup() -> None:
    """Leave the process group, if one is active, once every process has got here."""
    if is_distributed():
        # A collective's work object holds its tensors until a gloo worker thread drops it, which
        # can come after the caller has its result; dropped during interpreter shutdown, it needs
        # the GIL and aborts the process. A barrier holds no tensors and waits for that work.
        dist.barrier()
        dist.destroy_process_group()


def _comm_device() -> torch.device:
    # NCCL only moves CUDA tensors; gloo only CPU ones
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else torch.device("cpu")
