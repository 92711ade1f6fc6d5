"""One ``wm-paper`` training step on this machine (batch 1: a 6-step pushforward rollout from a
random start, the whole stage-2 loss, backward, AdamW), the window encoded in the step against
its planes read from the aligned cache (``data.cache_labels``: encoded once, stored in
float16; the labels moved in the step), alternating, untrained weights.

    python benchmarks/tools/paper_step.py [--rounds 3]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import torch

from t3fast.data.synthetic import SyntheticDriving
from t3fast.presets import autoencoder_size, preset
from t3fast.training.world_model.task import WorldModelTask, build_world_model
from t3fast.training.world_model.windows import collate_windows, ego_aligned_window


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    torch.manual_seed(0)
    cfg = preset("wm-paper")
    cfg.autoencoder = autoencoder_size("paper")
    task = WorldModelTask.__new__(WorldModelTask)  # the step only: no stage-1 checkpoint to read
    task.cfg = cfg
    model = build_world_model(cfg).train()
    optimizer = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    batch = collate_windows([SyntheticDriving("val", 1, 20, stride=9)[0]])
    cached = ego_aligned_window(model, batch.occ, batch.ego_poses)[0].map(lambda p: p.half().float())

    def step(planes) -> float:
        torch.manual_seed(1)  # the same rollout start and query points
        start = time.perf_counter()
        loss, _ = task.training_step(model, replace(batch, planes=planes))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        return time.perf_counter() - start

    for r in range(args.rounds):
        encoded, read = step(None), step(cached)
        print(f"round {r}: encoded in the step {encoded:.2f} s, cached planes {read:.2f} s, "
              f"ratio {encoded / read:.2f}", flush=True)


if __name__ == "__main__":
    main()
