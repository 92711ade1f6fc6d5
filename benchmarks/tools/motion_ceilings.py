"""How much better agent motion is worth: the label-space tracker along the TRUE ego poses with
the present's agents moved by different velocity estimates and by their true motion.

``python benchmarks/tools/motion_ceilings.py [--split test --scenes 10 --stride 8 --windows 40]``

Rows (Avg mIoU, moving-class Avg mIoU, IoU; classes absent from the windows skipped):

* ``warp_gt_ego``: nothing moves; ``track_gt_ego``: the tracker (last-step centroid velocity);
* ``chain_blend``: the last-step velocity averaged with the two-step mean along the matched
  chain (present -> previous -> the one before), a classical alternative;
* ``true_velocity``: each agent's box velocity over the last step, extrapolated (an oracle of
  the present's motion); ``true_turn``: that velocity turned by the box's true yaw rate over
  the last step at every future step (constant turn rate and speed, the best a kinematic
  extrapolation of the present state can do); ``true_motion``: each agent's true future box
  motion (the ceiling).

An agent (BEV component) takes the box whose present centre is nearest its centroid (within
6 voxels) and seen until the horizon; the others keep the tracker's velocity.

The same motions drawn as boxes instead of moving voxels (:mod:`t3fast.agents.boxes`):

* ``fitted_boxes``: each agent's box fitted to its columns in the five observed frames, moved by
  the fitted velocity (a classical tracker of boxes; agents without a trusted fit keep the
  tracker's voxels);
* ``box_true_velocity``, ``box_true_turn``, ``box_true_motion``: the agents' true present
  boxes moved as the rows above (the true boxes' sizes and sub-cell positions).
"""

from __future__ import annotations

import argparse

import torch

from t3fast.agents.boxes import draw_agent_boxes, fit_agent_boxes
from t3fast.agents.tracker import TRACK_GATE, agent_velocities, chained_velocities, frame_agents, move_agents
from t3fast.data.classes import AGENT_CLASSES, FREE, GRID_LOWER, VOXEL_SIZE
from t3fast.data.sample import NUM_FUTURE, PRESENT
from t3fast.data.synthetic import SyntheticDriving
from t3fast.data.synthetic.world import ON_GROUND, z_level
from t3fast.evaluation.world_model import MethodOutput, evaluate_many, track_gt_ego_method, warp_gt_ego_method
from t3fast.models.ego_motion import compose, planar_poses, relative, unwarp_sequence, warp_sequence

AGENTS = torch.tensor(AGENT_CLASSES, dtype=torch.uint8)
OWNER_CELLS = 6.0  # voxels between a component's centroid and its box centre to count as that agent


def velocities(now: dict, before: dict, older: dict, blend: bool) -> torch.Tensor:
    """Per present component, cells per step: the tracker's last-step centroid displacement and,
    with ``blend``, its mean with the two-step displacement along the matched chain."""
    gate = TRACK_GATE / VOXEL_SIZE
    v = agent_velocities(now, before, gate)
    return (v + chained_velocities(now, before, older, gate)) / 2 if blend else v


def box_shifts(now: dict, boxes: torch.Tensor, valid: torch.Tensor, mode: str) -> dict[int, torch.Tensor]:
    """Component -> ``[S, 2]`` voxel shifts from its box: the true future motion, or the last
    step's velocity extrapolated straight (``true_velocity``) or turning at the last step's yaw
    rate (``true_turn``)."""
    centres = (boxes[:, :, :2].double() - torch.tensor(GRID_LOWER[:2], dtype=torch.float64)) / VOXEL_SIZE - 0.5
    if now["cls"].shape[0] == 0 or not valid[PRESENT].any():
        return {}
    dist = (now["centroid"][:, None] - centres[PRESENT][None]).norm(dim=-1)
    dist[:, ~valid[PRESENT]] = float("inf")
    near, owner = dist.min(1)
    k = torch.arange(1, NUM_FUTURE + 1, dtype=torch.float64)[:, None]
    out = {}
    for c in range(now["cls"].shape[0]):
        a = int(owner[c])
        if near[c] <= OWNER_CELLS and bool(valid[PRESENT - 1 :, a].all()):
            velocity = centres[PRESENT, a] - centres[PRESENT - 1, a]
            if mode == "true_motion":
                out[c] = centres[PRESENT + 1 :, a] - centres[PRESENT, a]
            elif mode == "true_turn":
                last, now_pose = boxes[PRESENT - 1 : PRESENT + 1, a][:, [0, 1, 6]].double()
                turn = relative(last, now_pose)[2]  # the box's yaw change over the last step, wrapped
                headings = torch.zeros(k.shape[0], 3, dtype=torch.float64)
                headings[:, 2] = k[:, 0] * turn
                step = torch.cat([velocity, velocity.new_zeros(1)])  # the last step as a pose (x, y, 0)
                out[c] = compose(headings, step.expand_as(headings))[:, :2].cumsum(0)
            else:
                out[c] = k * velocity
    return out


def moved_agents(batch, mode: str) -> MethodOutput:
    """The present's agents moved per ``mode``, then into the true future ego frames."""
    poses = planar_poses(batch.ego_poses, PRESENT)
    past = warp_sequence(batch.past_occ[:, -3:-1], poses[:, PRESENT - 2 : PRESENT])
    k = torch.arange(1, NUM_FUTURE + 1, dtype=torch.float64)[:, None, None]
    scenes = []
    for n in range(batch.past_occ.shape[0]):
        present = batch.past_occ[n, -1]
        now, before, older = (frame_agents(f, AGENTS) for f in (present, past[n, 1], past[n, 0]))
        shift = k * velocities(now, before, older, blend=mode == "chain_blend")[None]
        if mode in ("true_velocity", "true_turn", "true_motion"):
            for c, s in box_shifts(now, batch.boxes[n], batch.box_valid[n], mode).items():
                shift[:, c] = s
        scenes.append(move_agents(present, now, shift.round().long(), FREE))
    return MethodOutput(labels=unwarp_sequence(torch.stack(scenes), poses[:, PRESENT + 1 :]))


def true_box_poses(boxes: torch.Tensor, valid: torch.Tensor, mode: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The present's true boxes ``[A]`` moved per ``mode``: planar poses ``[S, A, 3]`` in the
    present frame and which to draw (valid now; those without a last step stand still)."""
    now = boxes[PRESENT, :, [0, 1, 6]].double()
    moving = valid[PRESENT] & valid[PRESENT - 1]
    if mode == "box_true_motion":
        poses = boxes[PRESENT + 1 :, :, [0, 1, 6]].double()
        return torch.where(moving[None, :, None], poses, now), valid[PRESENT] & (valid[PRESENT + 1 :] | ~moving)
    last = boxes[PRESENT - 1, :, [0, 1, 6]].double()
    if mode == "box_true_velocity":  # the last step's displacement again and again, the heading kept
        velocity = torch.cat([now[:, :2] - last[:, :2], now.new_zeros(now.shape[0], 1)], 1)
        k = torch.arange(1, NUM_FUTURE + 1, dtype=torch.float64)[:, None, None]
        poses = now[None] + k * velocity[None]
    else:  # the last step as a pose in the box's own frame, composed again: constant turn rate
        step, pose, steps = relative(last, now), now, []
        for _ in range(NUM_FUTURE):
            pose = compose(pose, step)
            steps.append(pose)
        poses = torch.stack(steps)
    return torch.where(moving[None, :, None], poses, now), valid[PRESENT].expand(NUM_FUTURE, -1)


def boxed_agents(batch, mode: str) -> MethodOutput:
    """The present's agents drawn as boxes moved per ``mode`` into the true future ego frames."""
    poses = planar_poses(batch.ego_poses, PRESENT).double()
    k = torch.arange(1, NUM_FUTURE + 1, dtype=torch.float64)[:, None, None]
    scenes, draws = [], []
    for n in range(batch.past_occ.shape[0]):
        present = batch.past_occ[n, -1]
        if mode == "fitted_boxes":
            now, fit = fit_agent_boxes(batch.past_occ[n], poses[n, : PRESENT + 1])  # now: the present's agents
            previous = warp_sequence(batch.past_occ[n : n + 1, -2:-1], poses[n : n + 1, PRESENT - 1 : PRESENT].float())
            before = frame_agents(previous[0, 0], AGENTS)
            shift = (k * velocities(now, before, before, blend=False)[None]).round().long()
            scenes.append(move_agents(present, now, shift, FREE, keep=~fit.drawn))
            d = fit.drawn
            centres = fit.centre[d][None] + k * fit.velocity[d][None]
            yaws = fit.yaw[d].expand(NUM_FUTURE, -1)
            draws.append((centres, yaws, fit.length[d], fit.width[d], fit.bottom[d], fit.top[d], fit.label[d], None))
        else:
            now = frame_agents(present, AGENTS)
            scenes.append(present.masked_fill(now["mask"], FREE).expand(NUM_FUTURE, *present.shape).clone())
            box_poses, drawn = true_box_poses(batch.boxes[n], batch.box_valid[n], mode)
            boxes = batch.boxes[n, PRESENT].double()
            tops = torch.tensor([z_level(float(h)) for h in boxes[:, 5]], dtype=torch.long)
            draws.append((box_poses[..., :2], box_poses[..., 2], boxes[:, 3], boxes[:, 4],
                          torch.full_like(tops, ON_GROUND), tops, batch.box_labels[n], drawn))
    labels = unwarp_sequence(torch.stack(scenes), poses[:, PRESENT + 1 :].float())
    for n, (centres, yaws, length, width, bottom, top, label, drawn) in enumerate(draws):
        for s in range(NUM_FUTURE):
            d = torch.ones_like(label, dtype=torch.bool) if drawn is None else drawn[s]
            draw_agent_boxes(labels[n, s], centres[s, d], yaws[s, d], length[d], width[d], bottom[d], top[d],
                             label[d], poses[n, PRESENT + 1 + s])
    return MethodOutput(labels=labels)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--split", default="test", choices=["train", "val", "test"])
    parser.add_argument("--scenes", type=int, default=10)
    parser.add_argument("--stride", type=int, default=8)
    parser.add_argument("--windows", type=int, default=40)
    args = parser.parse_args()
    windows = SyntheticDriving(args.split, args.scenes, stride=args.stride)
    methods = {"warp_gt_ego": warp_gt_ego_method, "track_gt_ego": track_gt_ego_method}
    oracles = ("chain_blend", "true_velocity", "true_turn", "true_motion")
    methods.update({m: (lambda b, m=m: moved_agents(b, m)) for m in oracles})
    boxes = ("fitted_boxes", "box_true_velocity", "box_true_turn", "box_true_motion")
    methods.update({m: (lambda b, m=m: boxed_agents(b, m)) for m in boxes})
    records = evaluate_many(methods, windows, list(range(min(len(windows), args.windows))), absent="skip")
    print(f"{args.split}, {args.scenes} scenes, {min(len(windows), args.windows)} windows, true ego poses")
    print("| agents moved by | Avg mIoU | moving-class mIoU | IoU |\n|---|---:|---:|---:|")
    for name, r in records.items():
        print(f"| {name} | {r['miou']['avg']:.2f} | {r['miou_moving']['avg']:.2f} | {r['iou']['avg']:.2f} |")


if __name__ == "__main__":
    main()
