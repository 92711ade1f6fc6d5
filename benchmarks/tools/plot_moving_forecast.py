"""A forecast moving the other agents, next to the tracker and the truth:
``python benchmarks/tools/plot_moving_forecast.py CKPT OUT.png [--split test --scenes 10 --stride 8]``.

Picks the window of the split whose agents move farthest in 3 s (from the boxes) and draws the
present frame, then at +1, +2 and +3 s: the world model's forecast rendered along the TRUE future
ego poses (``t3former_gt_ego``, so only the agents' motion differs), the tracker baseline along
the same poses (``track_gt_ego``), and the ground truth.
"""

from __future__ import annotations

import torch
from window_tool import model_windows_out

from t3fast.data.sample import PRESENT, collate_samples
from t3fast.evaluation.baselines import track_gt_ego
from t3fast.models.ego_motion import planar_poses
from t3fast.viz.bev import comparison_figure


def motion_in_window(sample) -> float:
    """Metres the agents seen now and 3 s later move in between, summed."""
    seen = sample.box_valid[PRESENT] & sample.box_valid[-1]
    return float((sample.boxes[-1, seen, :2] - sample.boxes[PRESENT, seen, :2]).norm(dim=-1).sum())


@torch.no_grad()
def main() -> None:
    model, windows, out = model_windows_out(__doc__)
    index = max(range(len(windows)), key=lambda i: motion_in_window(windows[i]))
    sample = windows[index]
    batch = collate_samples([sample])
    poses = planar_poses(batch.ego_poses, PRESENT)[:, PRESENT + 1 :]
    forecast = model.forecast(batch.past_occ, batch.ego_poses[:, : PRESENT + 1], future_actions=poses).labels[0]
    tracked = track_gt_ego(batch.past_occ, batch.ego_poses)[0]
    rows = [("T3Former", forecast.numpy()), ("tracker", tracked.numpy()), ("truth", sample.future_occ.numpy())]
    figure = comparison_figure(sample.past_occ[-1].numpy(), rows, steps=[1, 3, 5])
    figure.save(out, optimize=True)
    print(f"{sample.scene} from frame {sample.start}: wrote {out}")


if __name__ == "__main__":
    main()
