"""Learning curves of a route-planner run (``t3fast train-planner``):
``python benchmarks/tools/plot_planner_curves.py METRICS.jsonl OUT.png``.

Left: the training batches' mean position error next to constant turn rate's on the same
batches. Middle and right: validation mean-L2 (over 1-3 s) and L2 at 3 s every ``eval_every``
steps, with and without the route command, constant turn rate as a flat line and 0.8x it (the
target) dotted.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
from curves import label_panel, read_events, run


def main(metrics: Path, out: Path) -> None:
    train, evals = read_events(metrics)
    fig, (left, *panels) = plt.subplots(1, 3, figsize=(17, 4.5))
    steps = [r["step"] for r in train]
    left.plot(steps, [r["values"]["plan_l2"] for r in train], label="route planner")
    left.plot(steps, [r["values"]["ctr_l2"] for r in train], ls="--", label="constant turn rate")
    label_panel(left, "mean position error over 6 steps (m)", "training (batch means, command dropped from a share)")
    at = [r["step"] for r in evals]
    for panel, (key, what) in zip(panels, (("l2_mean", "mean-L2 over 1-3 s"), ("l2_3s", "L2 at 3 s"))):
        panel.plot(at, [r["values"][f"command_{key}"] for r in evals], "o-", label="with the command")
        panel.plot(at, [r["values"][f"no_command_{key}"] for r in evals], "o-", label="without")
        ctr = evals[0]["values"][f"ctr_{key}"]
        panel.axhline(ctr, ls="--", color="tab:red", label="constant turn rate")
        panel.axhline(0.8 * ctr, ls=":", color="tab:red", label="0.8x constant turn rate")
        label_panel(panel, f"{what} (m, val)", f"validation: {what}")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    run(main, __doc__)
