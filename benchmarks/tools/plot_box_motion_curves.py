"""Learning curves of a box-motion run (``t3fast train-box-motion``):
``python benchmarks/tools/plot_box_motion_curves.py METRICS.jsonl OUT.png``.

Left: the training batches' class-balanced landing error (metres) next to the box tracker's (the
network at zero) on the same batches. Right: the same error on the held-out scenes' agents at 1,
2 and 3 s and over all steps, the box tracker's as flat dashed lines.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
from curves import label_panel, read_events, run


def main(metrics: Path, out: Path) -> None:
    train, evals = read_events(metrics)
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5))
    steps = [r["step"] for r in train]
    left.plot(steps, [r["values"]["loss"] for r in train], color="tab:blue", label="network")
    left.plot(steps, [r["values"]["tracker"] for r in train], color="tab:blue", ls="--", label="box tracker")
    label_panel(left, "landing error, mean over 6 steps (m)", "training batches")
    at = [r["step"] for r in evals]
    for key, color in zip(("1s", "2s", "3s", None), ("tab:blue", "tab:orange", "tab:green", "black")):
        name = "all steps" if key is None else key
        suffix = "" if key is None else f"_{key}"
        right.plot(at, [r["values"][f"net{suffix}"] for r in evals], "o-", color=color, label=f"network, {name}")
        right.axhline(evals[0]["values"][f"tracker{suffix}"], ls="--", color=color, label=f"box tracker, {name}")
    label_panel(right, "landing error (m, held-out scenes)", "held-out scenes")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    run(main, __doc__)
