"""Learning curves of a stage-2 run: ``python benchmarks/tools/plot_stage2_curves.py METRICS.jsonl OUT.png``.

Left: the training terms (latent loss next to the copy forecast's, or on the labels path the
triplane and occupancy losses; where logged, the flow error on moving agents and the drift of
parked ones). Middle: validation Avg mIoU every ``eval_every``
steps, along the planned and along the true ego poses, with the baselines scored once at step 0
on the same windows as flat lines. Right: the same for the moving classes' mIoU.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
from curves import label_panel, read_events, run

BASELINES = {"warp_gt_ego": "warp, true poses", "track_gt_ego": "tracker, true poses",
             "warp_const_vel": "warp, const. velocity", "track_const_vel": "tracker, const. velocity"}


def main(metrics: Path, out: Path) -> None:
    train, evals = read_events(metrics)
    fig, (left, *panels) = plt.subplots(1, 3, figsize=(17, 4.5))
    steps = [r["step"] for r in train]
    logged = train[0]["values"]
    twin = left.twinx()
    if "latent" in logged:  # the cached-window losses
        left.plot(steps, [r["values"]["latent"] for r in train], label="latent loss")
        left.plot(steps, [r["values"]["copy_latent"] for r in train], label="latent loss of the copy forecast",
                  ls="--")
        left.set_ylabel("weighted L1 + L2")
    else:  # the labels path: triplane and occupancy terms
        left.plot(steps, [r["values"]["triplane"] for r in train], label="triplane loss")
        left.set_ylabel("L1 + L2")
        twin.plot(steps, [r["values"]["occupancy"] for r in train], color="tab:purple", alpha=0.6,
                  label="occupancy loss (CE + Lovasz)")
    left.set_xlabel("step")
    for key, colour, name in (("flow_moving", "tab:red", "displacement error on moving agents"),
                              ("flow_parked", "tab:orange", "displacement of parked agents")):
        if key in logged:
            twin.plot(steps, [r["values"][key] for r in train], color=colour, alpha=0.6, label=name)
            twin.set_ylabel("plane cells")
    left.legend(loc="upper left", fontsize=8)
    if twin.lines:
        twin.legend(loc="upper right", fontsize=8)
    else:  # nothing logged on the second axis (the cached-window losses)
        twin.remove()
    left.set_title("training (batch means)")
    at = [r["step"] for r in evals]
    first = evals[0]["values"]
    for panel, (suffix, what) in zip(panels, (("", "Avg mIoU"), ("_moving", "moving-class Avg mIoU"))):
        if f"gt_ego_miou{suffix}_avg" in first:  # ego-aligned models only
            panel.plot(at, [r["values"][f"gt_ego_miou{suffix}_avg"] for r in evals], "o-",
                       label="t3former, true poses")
        panel.plot(at, [r["values"][f"miou{suffix}_avg"] for r in evals], "o-", label="t3former, planned poses")
        for (key, name), colour in zip(BASELINES.items(), ("tab:green", "tab:red", "tab:purple", "tab:brown")):
            if f"{key}_miou{suffix}_avg" in first:
                panel.axhline(first[f"{key}_miou{suffix}_avg"], ls="--", color=colour, label=name)
        label_panel(panel, f"{what} (val)", f"validation: {what}")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    run(main, __doc__)
