"""Learning curves of a motion-head run (``t3fast train-motion``):
``python benchmarks/tools/plot_motion_curves.py METRICS.jsonl OUT.png``.

Left: the training batches' per-agent displacement error (moving and parked agents) next to the
tracker's on the same batches. Middle: validation error of the moving agents at 1, 2 and 3 s,
the tracker's as flat dashed lines. Right: validation mean error of the moving and the parked
agents, the tracker's dashed.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
from curves import label_panel, read_events, run


def main(metrics: Path, out: Path) -> None:
    train, evals = read_events(metrics)
    fig, (left, middle, right) = plt.subplots(1, 3, figsize=(17, 4.5))
    steps = [r["step"] for r in train]
    for kind, color in (("moving", "tab:blue"), ("parked", "tab:orange")):
        left.plot(steps, [r["values"][f"flow_{kind}"] for r in train], color=color, label=f"motion head, {kind}")
        left.plot(steps, [r["values"][f"tracker_{kind}"] for r in train], color=color, ls="--",
                  label=f"tracker, {kind}")
    label_panel(left, "per-agent error, mean over 6 steps (plane cells)", "training batches")
    at = [r["step"] for r in evals]
    for panel, keys, title in ((middle, ("moving_1s", "moving_2s", "moving_3s"), "validation: moving agents"),
                               (right, ("moving", "parked"), "validation: mean over 0.5-3 s")):
        for key, color in zip(keys, ("tab:blue", "tab:orange", "tab:green")):
            panel.plot(at, [r["values"][f"head_{key}"] for r in evals], "o-", color=color, label=f"head, {key}")
            panel.axhline(evals[0]["values"][f"tracker_{key}"], ls="--", color=color, label=f"tracker, {key}")
        label_panel(panel, "per-agent error (plane cells, val)", title)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    run(main, __doc__)
