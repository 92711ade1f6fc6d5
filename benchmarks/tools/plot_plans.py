"""Planned against true ego trajectories at a junction and when the ego brakes:
``python benchmarks/tools/plot_plans.py CKPT OUT.png [--split test --scenes 10 --stride 8]``.

Picks two windows of the split: the turn (route command left or right) where constant speed and
turn rate is farthest off at 3 s, and the straight-on window whose ego loses the most speed over
the 3 s (it brakes behind traffic or for a light). Each is drawn as its present frame (top-down,
forward up) with the true future (cyan), constant turn rate (red), the model's plan without the
route command (orange) and with it (green), the 3 s errors in the caption.
"""

from __future__ import annotations

import numpy as np
import torch
from PIL import Image, ImageDraw
from window_tool import model_windows_out

from t3fast.data.route import COMMANDS, STRAIGHT
from t3fast.data.sample import PRESENT, collate_samples
from t3fast.models.planner import constant_turn_rate
from t3fast.viz.bev import bev_image, sample_frame_boxes

CTR_COLOUR, NO_COMMAND_COLOUR = (255, 60, 60), (255, 160, 0)


def ctr_error(sample) -> float:
    """Metres between constant turn rate's and the true position at 3 s."""
    plan = constant_turn_rate(sample.past_actions[None], 6)[0].cumsum(0)
    return float((plan[-1] - sample.trajectory[-1]).norm())


def slowdown(sample) -> float:
    """Metres per step the ego's last past step is longer than its last future one."""
    return float(sample.past_actions[-1].norm() - sample.future_actions[-1].norm())


@torch.no_grad()
def panel(model, sample, title: str) -> Image.Image:
    batch = collate_samples([sample])
    past, poses = batch.past_occ, batch.ego_poses[:, : PRESENT + 1]
    command = batch.command if model.reads_command else None
    with_command = model.forecast(past, poses, command=command).trajectory[0].numpy()
    without = model.forecast(past, poses).trajectory[0].numpy()
    ctr = constant_turn_rate(batch.past_actions, 6)[0].cumsum(0).numpy()
    truth = sample.trajectory.numpy()
    image = bev_image(sample.past_occ[-1].numpy(), sample_frame_boxes(sample, PRESENT), trajectory=with_command,
                      true_trajectory=truth, more_paths=[(ctr, CTR_COLOUR), (without, NO_COMMAND_COLOUR)])
    err = {name: float(np.linalg.norm(path[-1] - truth[-1])) for name, path in
           (("constant turn rate", ctr), ("no command", without), ("command", with_command))}
    caption = (f"{title}: {sample.scene} t{sample.start:02d}, command '{COMMANDS[int(sample.command)]}'\n"
               "L2 at 3 s: " + ", ".join(f"{k} {v:.1f} m" for k, v in err.items()))
    out = Image.new("RGB", (image.width, image.height + 30), (255, 255, 255))
    out.paste(image, (0, 30))
    ImageDraw.Draw(out).multiline_text((2, 2), caption, fill=(0, 0, 0))
    return out


def main() -> None:
    model, split, out = model_windows_out(__doc__)
    windows = list(split)
    turns = [w for w in windows if int(w.command) != STRAIGHT]
    straight = [w for w in windows if int(w.command) == STRAIGHT]
    panels = []
    if turns:
        panels.append(panel(model, max(turns, key=ctr_error), "junction"))
    panels.append(panel(model, max(straight, key=slowdown), "braking"))
    canvas = Image.new("RGB", (sum(p.width for p in panels) + 4 * (len(panels) - 1), panels[0].height), "white")
    x = 0
    for p in panels:
        canvas.paste(p, (x, 0))
        x += p.width + 4
    canvas.save(out, optimize=True)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
