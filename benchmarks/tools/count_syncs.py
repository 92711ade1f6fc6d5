"""Where the whole forecast waits on its data: the ops of one ``model.forecast`` whose result
the host must read (a scalar read, ``nonzero``, ``unique``, boolean masks: data-dependent
shapes), counted by the Python function that called them. On a GPU each is a host
synchronisation; the forecast captured in one CUDA graph (or compiled whole) has none.

    python benchmarks/tools/count_syncs.py [--model wm-small]
"""

from __future__ import annotations

import argparse
import traceback
from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.pretrained import load_world_model

#: aten ops whose output the host reads or whose output's shape depends on the values
SYNCING = {"_local_scalar_dense", "equal", "nonzero", "unique", "_unique2", "unique_dim", "unique_consecutive",
           "masked_select", "repeat_interleave", "bincount"}  # and aten.index with a boolean mask


class SyncCounter(TorchDispatchMode):
    """Counts the syncing ops run under it by op and by the t3fast function that ran them."""

    def __init__(self):
        super().__init__()
        self.by_op: Counter[str] = Counter()
        self.by_caller: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func._schema.name.split("::")[-1]
        indices = args[1] if name == "index" and len(args) > 1 else []
        boolean_index = any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in indices)
        if name in SYNCING or boolean_index:
            self.by_op["index (bool mask)" if boolean_index else name] += 1
            frames = [f for f in traceback.extract_stack() if "/t3fast/" in f.filename]
            if frames:
                f = frames[-1]
                self.by_caller[f"{f.filename.split('/t3fast/', 1)[1]}:{f.name}"] += 1
        return func(*args, **(kwargs or {}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="wm-small")
    args = parser.parse_args()
    model = load_world_model(args.model)
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    occ, poses = sample.occ[None, : PRESENT + 1], sample.ego_poses[None, : PRESENT + 1]
    counter = SyncCounter()
    with counter:
        model.forecast(occ, poses)
    print(f"{args.model}: {sum(counter.by_op.values())} syncing ops in one forecast")
    for name, count in counter.by_op.most_common():
        print(f"  {count:6d}  {name}")
    print("by caller:")
    for name, count in counter.by_caller.most_common(25):
        print(f"  {count:6d}  {name}")


if __name__ == "__main__":
    main()
