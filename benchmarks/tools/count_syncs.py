"""Where the whole forecast waits on its data: the ops of one ``model.forecast`` whose result
the host must read (a scalar read, ``nonzero``, ``unique``, boolean masks: data-dependent
shapes), counted by the Python function that called them. On a GPU each is a host
synchronisation; the forecast captured in one CUDA graph (or compiled whole) has none. Then the
same forecast as a GPU runs it, with the model and inputs on the meta device: its ops (each a
kernel launch there), reads and copies of host data; and how many ops a window more in the batch
adds when the forecast runs as on a GPU (:func:`~t3fast.host_syncs.sync_free`).

    python benchmarks/tools/count_syncs.py [--model wm-small] [--batch 4]
"""

from __future__ import annotations

import argparse

from t3fast.data.sample import PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.host_syncs import SyncCounter, sync_free
from t3fast.pretrained import load_world_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="wm-small")
    parser.add_argument("--batch", type=int, default=4, help="the batch the per-window ops are counted at")
    args = parser.parse_args()
    model = load_world_model(args.model)
    sample = SyntheticDriving("val", 1, 20, stride=9)[0]
    occ, poses = sample.occ[None, : PRESENT + 1], sample.ego_poses[None, : PRESENT + 1]
    counter = SyncCounter()
    with counter:
        model.forecast(occ, poses)
    print(f"{args.model}: {counter.total} syncing ops in one forecast, {counter.dispatched} ops dispatched, "
          f"{sum(counter.host_data.values())} tensors made from host data")
    for name, count in counter.by_op.most_common():
        print(f"  {count:6d}  {name}")
    print("by caller:")
    for name, count in counter.by_caller.most_common(25):
        print(f"  {count:6d}  {name}")
    dispatched = {}
    for batch in (1, args.batch):
        with sync_free(), SyncCounter() as counter:
            model.forecast(occ.expand(batch, *occ.shape[1:]), poses.expand(batch, *poses.shape[1:]))
        dispatched[batch] = counter.dispatched
    per_window = (dispatched[args.batch] - dispatched[1]) / max(args.batch - 1, 1)
    print(f"as a GPU runs it, batch 1: {dispatched[1]} ops; batch {args.batch}: {dispatched[args.batch]} "
          f"({per_window:.0f} a window more)")
    model.to("meta")
    meta = occ.to("meta"), poses.to("meta")
    model.forecast(*meta)  # the constants made once per device
    with SyncCounter() as gpu_like:
        model.forecast(*meta)
    print(f"as a GPU runs it (on meta): {gpu_like.total} syncing ops, {gpu_like.dispatched} ops dispatched, "
          f"{sum(gpu_like.host_data.values())} tensors made from host data")


if __name__ == "__main__":
    main()
