"""The memory traffic of one whole forecast as a GPU runs it: every op's inputs and outputs in
bytes (views excluded; an expanded input counted at its full size, so an upper bound), per
window of a batch, by the t3fast function that called the op. The model and inputs live on the
meta device under :func:`~t3fast.host_syncs.sync_free`: nothing is computed, so it runs in
seconds on any machine. A batched forecast on a GPU is bound by this traffic (an H100 moves
about 3 TB/s); the eager kernels each read and write their operands once.

    python benchmarks/tools/op_traffic.py [--model wm-small] [--batch 8] [--top 25]
"""

from __future__ import annotations

import argparse
import traceback
from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.host_syncs import sync_free, t3fast_caller
from t3fast.pretrained import load_world_model

VIEWS = {"view", "_unsafe_view", "expand", "slice", "select", "unsqueeze", "squeeze", "permute", "transpose", "t",
         "as_strided", "alias", "detach", "unbind", "split", "split_with_sizes", "chunk", "narrow", "unfold",
         "diagonal"}


class Traffic(TorchDispatchMode):
    """Bytes read and written by each op, and op counts, by calling function."""

    def __init__(self) -> None:
        super().__init__()
        self.bytes: Counter[str] = Counter()
        self.ops: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if func._schema.name.removeprefix("aten::") not in VIEWS:
            tensors = [t for t in tree_leaves((args, kwargs, out)) if isinstance(t, torch.Tensor)]
            caller = t3fast_caller(traceback.extract_stack()) or "(outside t3fast)"
            self.bytes[caller] += sum(t.numel() * t.element_size() for t in tensors)
            self.ops[caller] += 1
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="wm-small")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--top", type=int, default=25)
    args = parser.parse_args()
    model = load_world_model(args.model).to("meta")
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    occ = sample.occ[None, : PRESENT + 1].expand(args.batch, -1, -1, -1, -1).to("meta")
    poses = sample.ego_poses[None, : PRESENT + 1].expand(args.batch, -1, -1, -1).to("meta")
    with sync_free():
        model.forecast(occ, poses)  # the constants made once per device
        with Traffic() as traffic:
            model.forecast(occ, poses)
    total = sum(traffic.bytes.values())
    print(f"{args.model}, batch {args.batch}: {total / args.batch / 1e9:.2f} GB a window, "
          f"{sum(traffic.ops.values())} ops")
    for caller, nbytes in traffic.bytes.most_common(args.top):
        print(f"  {nbytes / args.batch / 1e6:8.1f} MB  {traffic.ops[caller]:5d} ops  {caller}")


if __name__ == "__main__":
    main()
