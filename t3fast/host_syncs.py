"""Where code waits on its data: the ops whose result the host must read (a scalar read,
``nonzero``, ``unique``, a boolean mask: data-dependent shapes). On a GPU each one is a host
synchronisation, and a step captured as one CUDA graph (or compiled whole) can hold none; nor
can it hold a copy of host data to the device, which waits too.

:class:`SyncCounter` counts them on any device (a CPU run counts what a GPU run would wait on),
by op and by the t3fast function that ran them::

    with SyncCounter() as counter:
        model.forecast(past_occupancy, past_poses)
    counter.by_caller.most_common()
"""

from __future__ import annotations

import traceback
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch.utils._python_dispatch import TorchDispatchMode

_sync_free: list[bool] = []


@contextmanager
def sync_free() -> Iterator[None]:
    """Run the forecast as a GPU run does on any device, the CPU included: fixed-size records
    where a CPU run compacts data-dependent ones on the host (:func:`reads_host`). For tests,
    and for compiling or capturing the forecast whole."""
    _sync_free.append(True)
    try:
        yield
    finally:
        _sync_free.pop()


def reads_host(device: torch.device | str) -> bool:
    """Whether code on ``device`` compacts data-dependent records on the host (the agents found
    in a frame, the voxels beyond the observed grid): on the CPU, where a read costs nothing and
    compacting saves work; not on an accelerator, where every read waits for the device, nor
    under :func:`sync_free`. Either way the results are the same."""
    return not _sync_free and torch.device(device).type == "cpu"


#: aten ops whose output the host reads (the linalg ops that check their results on the host among
#: them) or whose output's shape depends on the values
SYNCING = frozenset({"_local_scalar_dense", "_linalg_check_errors", "_linalg_eigh", "_linalg_svd", "linalg_eig",
                     "equal", "nonzero", "unique", "_unique2", "unique_dim", "unique_consecutive", "masked_select",
                     "repeat_interleave", "bincount"})


class SyncCounter(TorchDispatchMode):
    """Counts the syncing ops (:data:`SYNCING`, and indexing with a boolean mask) run under it:
    ``by_op`` (op name) and ``by_caller`` (``"module/path.py:function"`` of the innermost t3fast
    frame that ran it); ``host_data`` by caller (or ``"(outside t3fast)"``), the tensors made from host data
    (``torch.tensor``, ``new_tensor``; seen on the CPU) and the copies of a CPU tensor to
    another device (seen with the inputs on "meta"), each a copy that waits on a GPU, leaving
    out the constants made once per device (:mod:`t3fast.device_constants`); and
    ``dispatched``, every op run (views included): an upper bound of the kernels a GPU run
    launches, each costing microseconds of the host's time."""

    def __init__(self) -> None:
        super().__init__()
        self.by_op: Counter[str] = Counter()
        self.by_caller: Counter[str] = Counter()
        self.host_data: Counter[str] = Counter()
        self.dispatched = 0

    @property
    def total(self) -> int:
        """How many syncing ops ran."""
        return sum(self.by_op.values())

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.dispatched += 1
        name = func._schema.name.split("::")[-1]
        indices = args[1] if name in ("index", "index_put", "index_put_") and len(args) > 1 else []
        boolean_index = any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices or [])
        if name in SYNCING or boolean_index:
            self.by_op["index (bool mask)" if boolean_index else name] += 1
            self._count(self.by_caller, traceback.extract_stack())
        out = func(*args, **(kwargs or {}))
        source = args[1] if name == "copy_" else args[0] if name == "_to_copy" else None
        if name == "lift_fresh" or _to_device(source, out):
            stack = traceback.extract_stack()
            if not any(f.filename.endswith("device_constants.py") for f in stack):
                self._count(self.host_data, stack, outside="(outside t3fast)")
        return out

    @staticmethod
    def _count(counter: Counter[str], stack: traceback.StackSummary, outside: str | None = None) -> None:
        """Count one op for the innermost t3fast frame of ``stack`` that ran it (for ``outside``
        where none did, if given)."""
        caller = t3fast_caller(stack)
        if caller is not None:
            counter[caller] += 1
        elif outside is not None:
            counter[outside] += 1


def t3fast_caller(stack: traceback.StackSummary) -> str | None:
    """``"module/path.py:function"`` of the innermost t3fast frame of ``stack`` (this module's
    left out), or None where no t3fast code is on it."""
    frames = [f for f in stack if "/t3fast/" in f.filename and not f.filename.endswith("host_syncs.py")]
    return f"{frames[-1].filename.rsplit('/t3fast/', 1)[1]}:{frames[-1].name}" if frames else None


def _to_device(source: object, out: object) -> bool:
    """Whether a copy from ``source`` to ``out`` goes from the host to another device."""
    return (isinstance(source, torch.Tensor) and isinstance(out, torch.Tensor) and source.device.type == "cpu"
            and out.device.type != "cpu")
